"""What lensfit writes: result files written whole or not at all (``writers``), the HTML fit report
(``report``) and the figures (``plots``)."""
