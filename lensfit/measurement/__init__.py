"""Blur read from images: the measuring run over a stack (``measure``, with the rounds and
warm-up of ``pipeline``), the edges' geometry, the spot models (``psf``, ``diffraction``) and what a
raw developer did to the images (``processing``). The edge estimators are in :mod:`lensfit.estimators`."""
