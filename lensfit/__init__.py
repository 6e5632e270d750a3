"""lensfit: recover focal length, focus distance and f-number from defocus blur.

Submodules are imported on demand (``from lensfit import optics``), so that importing the
package stays cheap and never switches JAX to float64 as a side effect. Importing it does point
JAX's persistent compilation cache at ``~/.cache/lensfit/jax`` (``LENSFIT_JAX_CACHE=DIR`` moves it,
``off`` disables it; :mod:`lensfit.jaxcache`), so that scripts start as fast as the programs.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lensfit")
except PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__", "fit"]

from lensfit.jaxcache import enable_by_default as _enable_cache

_enable_cache()
del _enable_cache


def __getattr__(name: str):
    """``lensfit.fit`` without importing JAX when the package is imported: the fit package,
    which is callable (``lensfit.fit(samples)`` fits; ``lensfit/fit/__init__.py``)."""
    if name == "fit":
        import importlib

        return importlib.import_module("lensfit.fit")
    raise AttributeError(f"module 'lensfit' has no attribute {name!r}")
