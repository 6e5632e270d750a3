"""JAX's persistent compilation cache, on for the command-line tools and the library alike.

Compiled kernels are stored under ``$LENSFIT_JAX_CACHE`` (default
``~/.cache/lensfit/jax``), so that a second run of a CLI skips compilation, and the exported
traces of the batched solvers under its ``traces/`` (``lensfit.runtime.aot``), so that it skips tracing
too. Set ``LENSFIT_JAX_CACHE=off`` to disable both. ``import lensfit`` switches it on
(:func:`enable_by_default`) unless the program has set JAX's own cache folder.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

_SET_IN_ENVIRONMENT: set[str] = set()


def cache_folder() -> Path:
    """``$LENSFIT_JAX_CACHE``, else ``~/.cache/lensfit/jax`` (whether or not it is on)."""
    setting = os.environ.get("LENSFIT_JAX_CACHE", "")
    return Path(setting) if setting and setting.lower() != "off" else Path.home() / ".cache" / "lensfit" / "jax"


def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent cache at the lensfit cache folder; returns it (None if disabled)."""
    setting = os.environ.get("LENSFIT_JAX_CACHE", "")
    if setting.lower() == "off":
        for name in _SET_IN_ENVIRONMENT:  # not passed on to child processes either
            os.environ.pop(name, None)
        _SET_IN_ENVIRONMENT.clear()
        return None
    path = cache_folder()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache rather than fail
    settings = {"jax_compilation_cache_dir": str(path), "jax_persistent_cache_min_compile_time_secs": 0.2,
                "jax_persistent_cache_min_entry_size_bytes": 0}
    if "jax" in sys.modules:
        import jax

        for name, value in settings.items():
            jax.config.update(name, value)
    else:
        # JAX not imported yet (0.5 s; lensfit.measurement.measure imports it in the background while the
        # images are read): it takes these from the environment as it starts.
        for name, value in settings.items():
            os.environ[name.upper()] = str(value)
            _SET_IN_ENVIRONMENT.add(name.upper())
    from lensfit.runtime import aot

    traces = path / "traces"
    try:
        traces.mkdir(exist_ok=True)
        aot.set_store(traces)
    except OSError:
        aot.set_store(None)
    return path


def enable_by_default() -> Path | None:
    """The library's default (``import lensfit``, and so ``import synth``): the cache on, as the
    programs have it, so that a script's second run skips compilation too. Left off where
    ``LENSFIT_JAX_CACHE=off``, and where the program has pointed JAX's own cache elsewhere
    (``JAX_COMPILATION_CACHE_DIR``, or ``jax_compilation_cache_dir`` set before lensfit's import);
    a child of a lensfit process, which inherits lensfit's setting, takes it as its own."""
    if os.environ.get("LENSFIT_JAX_CACHE", "").lower() == "off":
        return None
    ours = str(cache_folder())
    if os.environ.get("JAX_COMPILATION_CACHE_DIR", ours) != ours:
        return None
    if "jax" in sys.modules:
        import jax

        if jax.config.jax_compilation_cache_dir not in (None, "", ours):
            return None
    return enable_compilation_cache()
