"""JAX's persistent compilation cache, switched on by the command-line tools (not on import).

Compiled kernels are stored under ``$LENSFIT_JAX_CACHE`` (default
``~/.cache/lensfit/jax``), so that a second run of a CLI skips compilation, and the exported
traces of the batched solvers under its ``traces/`` (``lensfit.aot``), so that it skips tracing
too. Set ``LENSFIT_JAX_CACHE=off`` to disable both.
"""

from __future__ import annotations

import os
from pathlib import Path


def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent cache at the lensfit cache folder; returns it (None if disabled)."""
    setting = os.environ.get("LENSFIT_JAX_CACHE", "")
    if setting.lower() == "off":
        return None
    path = Path(setting) if setting else Path.home() / ".cache" / "lensfit" / "jax"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache rather than fail
    import jax

    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    from lensfit import aot

    traces = path / "traces"
    try:
        traces.mkdir(exist_ok=True)
        aot.set_store(traces)
    except OSError:
        aot.set_store(None)
    return path
