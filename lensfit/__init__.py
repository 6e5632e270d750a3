"""lensfit: recover focal length, focus distance and f-number from defocus blur.

    >>> import lensfit
    >>> samples, result, rounds = lensfit.measure_and_fit("out/demo")   # doctest: +SKIP
    >>> result.settings["a"]["f_number"].ci95                            # doctest: +SKIP

The package is grouped by job: ``io`` (images, EXIF, stack.toml, the samples table),
``calibration`` (targets and the camera), ``measurement`` (blur from images) with the edge
``estimators``, ``fitting`` (the circle-of-confusion model), ``outputs`` (result files, report,
figures), ``capture`` (planning a capture), ``optics`` (thin-lens formulas) and ``runtime``
(processes, parallel work, JAX's caches). The names below, and the subpackages, are imported on
first use (``lazy_loader``), so that importing the package stays cheap and never switches JAX
to float64 as a side effect. Importing it does point JAX's persistent compilation cache at
``~/.cache/lensfit/jax`` (``LENSFIT_JAX_CACHE=DIR`` moves it, ``off`` disables it;
:mod:`lensfit.runtime.jaxcache`), so that scripts start as fast as the programs.
"""

from importlib.metadata import PackageNotFoundError, version

import lazy_loader

try:
    __version__ = version("lensfit")
except PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0.0.0+unknown"

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submodules=["bench", "calibration", "capture", "cli", "errors", "estimators", "fitting", "io", "measurement",
                "optics", "outputs", "runtime"],
    submod_attrs={
        "fitting": ["fit", "FitResult", "Estimate", "Outcome", "results_document", "write_results",
                    "compare_with_truth", "cramer_rao"],
        "measurement.measure": ["measure", "Measurement"],
        "measurement.pipeline": ["measure_and_fit"],
        "io.stack": ["load_stack"],
        "errors": ["InputError"],
    },
)
__all__ = ["__version__", *__all__]

from lensfit.runtime.jaxcache import enable_by_default as _enable_cache  # noqa: E402

_enable_cache()
del _enable_cache
