"""How lensfit runs: process set-up (``running``), images in parallel (``parallel``), stage clocks
(``clock``) and JAX's compilation caches (``jaxcache``, ``aot``)."""
