"""How lensfit runs: process set-up (``running``), images in parallel (``parallel``), stage clocks
(``clock``) and compiled code kept between processes (``jaxcache``)."""
