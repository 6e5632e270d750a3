"""synth: a thin-lens renderer whose defocus blur is known exactly."""

from lensfit import __version__

__all__ = ["__version__"]
