"""lensfit: recover focal length, focus distance and f-number from defocus blur.

Submodules are imported on demand (``from lensfit import optics``), so that importing the
package stays cheap and never switches JAX to float64 as a side effect.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lensfit")
except PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__", "fit"]


def __getattr__(name: str):
    """``lensfit.fit`` without importing JAX when the package is imported: the fit package,
    which is callable (``lensfit.fit(samples)`` fits; ``lensfit/fit/__init__.py``)."""
    if name == "fit":
        import importlib

        return importlib.import_module("lensfit.fit")
    raise AttributeError(f"module 'lensfit' has no attribute {name!r}")
