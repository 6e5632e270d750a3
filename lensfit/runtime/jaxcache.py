"""Compiled code kept between processes: JAX's persistent compilation cache and exported traces,
on for the command-line tools and the library alike.

Compiled kernels are stored under ``$LENSFIT_JAX_CACHE`` (default ``~/.cache/lensfit/jax``), so
that a second run of a CLI skips compilation, and the exported traces of the batched solvers
under its ``traces/``, so that it skips tracing too. Set ``LENSFIT_JAX_CACHE=off`` to disable
both. ``import lensfit`` switches them on (:func:`enable_by_default`) unless the program has set
JAX's own cache folder.

Traces: tracing a batched solver with closed-form pixel profiles takes seconds, in every new
process (the persistent compilation cache keeps compiled code, not traces). A function called
through :func:`call` is traced and exported (``jax.export``) at its first use with a given
argument shape and stored beside the compilation cache, and on the CPU its compiled executable
too (``jax.experimental.serialize_executable``): later processes load the executable (20-80 ms a
function; where there is none, the stored trace is compiled afresh once and its executable
stored). Deserializing a trace and compiling it from JAX's persistent cache instead costs about
0.17 s a function, 0.1 s of it fetching the compiled code by a key that needs the trace lowered
again: 1.9 s of CPU for the eleven functions of a demo fit against 0.5 s loaded as executables.
Only where the cache is on (:func:`enable_compilation_cache`); otherwise, and on any failure to
read or write the store, the plain ``jax.jit`` path runs (same results). The file name carries
the JAX version, the backend and a hash of the source of the modules the function depends on,
so a change of any of them traces afresh; an executable's also the arguments' tree, jaxlib's
version, ``XLA_FLAGS`` and the processor (its model and instruction-set flags: the code is
compiled for this machine's).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import sys
import threading
from functools import partial
from pathlib import Path
from typing import Any, Callable

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
    traces = path / "traces"
    try:
        traces.mkdir(exist_ok=True)
        set_store(traces)
    except OSError:
        set_store(None)
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


# --------------------------------------------------------------------------- exported traces

_DIR: list[Path | None] = [None]
_LOADED: dict[str, Callable] = {}
_LOCK = threading.Lock()
_KEY_LOCKS: dict[str, threading.Lock] = {}  # one per function: loading one never waits on another
_HASHES: dict[tuple[str, ...], str] = {}  # the source of a running process does not change


def set_store(path: Path | None) -> None:
    """Where exported functions are kept (None: nowhere; plain jit)."""
    _DIR[0] = path
    _LOADED.clear()


def _source_hash(modules: tuple[str, ...]) -> str:
    if modules in _HASHES:
        return _HASHES[modules]
    h = hashlib.sha256()
    for name in modules:
        spec = importlib.util.find_spec(name)
        h.update(name.encode())
        if spec is not None and spec.origin:
            h.update(Path(spec.origin).read_bytes())
    _HASHES[modules] = h.hexdigest()[:16]
    return _HASHES[modules]


def _key(name: str, args, static: dict[str, Any], modules: tuple[str, ...]) -> str:
    import jax

    shapes = ",".join(f"{getattr(a, 'dtype', type(a).__name__)}{list(getattr(a, 'shape', ()))}"
                      for a in jax.tree_util.tree_leaves(args))
    text = f"{name}|{jax.__version__}|{jax.default_backend()}|{sorted(static.items())}|{shapes}|{_source_hash(modules)}"
    return name + "-" + hashlib.sha256(text.encode()).hexdigest()[:24]


def _export(fn: Callable, args, static: dict[str, Any]):
    """``jax.export`` of ``fn`` (jitted with ``static``) at ``args``. Calls into LAPACK (Cholesky,
    SVD) carry no cross-version guarantee; the store is keyed by the JAX version, so they are
    allowed by name."""
    from jax import export

    allowed: list[str] = []
    for _ in range(20):
        try:
            checks = [export.DisabledSafetyCheck.custom_call(t) for t in allowed]
            return export.export(jax_jit(fn, static), disabled_checks=checks)(*args)
        except ValueError as exc:
            found = set(re.findall(r"stablehlo\.custom_call @(\w+)", str(exc))) - set(allowed)
            if "no compatibility guarantees" not in str(exc) or not found:
                raise
            allowed.extend(sorted(found))
    raise RuntimeError("could not export: too many custom calls")


def jax_jit(fn: Callable, static: dict[str, Any]):
    import jax

    return jax.jit(partial(fn, **static))


def call(name: str, fn: Callable, args: tuple, static: dict[str, Any] | None = None,
         modules: tuple[str, ...] = (), kernels: bool = True) -> Any:
    """``fn(*args, **static)`` through the store (see the module docstring). ``fn`` must be pure
    and its result a pytree of arrays; ``modules``: the names of the modules whose source defines
    it (their change invalidates the stored trace). ``kernels=False``: ``fn`` calls none of
    LAPACK's kernels (no linear solve), so loading its executable needs no preparing of them
    (0.2 s: it imports ``scipy.linalg``); checked when the executable is compiled (one that
    calls them is then not kept)."""
    static = static or {}
    store = _DIR[0]
    if store is None:
        return _jitted(fn, static)(*args)
    key = _key(name, args, static, modules)
    runner = _LOADED.get(key)
    if runner is None:
        with _LOCK:
            lock = _KEY_LOCKS.setdefault(key, threading.Lock())
        with lock:  # one thread loads a function (lensfit.measurement.measure loads in the background), others wait
            runner = _LOADED.get(key)
            if runner is None:
                runner = _executable(store, key, args, lambda: _load_or_export(store / f"{key}.jaxexport", fn,
                                                                                args, static), kernels)
                _LOADED[key] = runner
    return runner(*args)


def _executable_path(store: Path, key: str, args, kernels: bool = True) -> Path | None:
    """Where the compiled executable of ``key`` for these arguments is kept; None where
    executables are not kept (a backend other than the CPU, or a JAX without the hook that
    prepares LAPACK's kernels, without which a loaded executable that calls them crashes)."""
    import jax

    if jax.default_backend() != "cpu" or (kernels and not _prepare_custom_calls()):
        return None
    import jaxlib

    tree = str(jax.tree_util.tree_structure(args))
    flags = os.environ.get("XLA_FLAGS", "")  # compiled under them (threads, code generation)
    tag = hashlib.sha256(f"{tree}|{jaxlib.__version__}|{_processor()}|{flags}".encode()).hexdigest()[:12]
    return store / f"{key}-{tag}.jaxexe"


_PREPARED: list[bool] = []
_PREPARING = threading.Lock()  # not _LOCK: other keys' loading need not wait for SciPy's import


def _prepare_custom_calls() -> bool:
    """LAPACK's kernels (the solves' Cholesky and SVD) take their routines from SciPy when a
    function that uses them is first lowered; a loaded executable is never lowered, so this is
    done before one is loaded (one that called them without it segfaulted, jaxlib 0.10). False
    where this JAX has no such hook: then no executable is kept or loaded."""
    with _PREPARING:
        if not _PREPARED:
            try:
                from jax._src.lax import linalg

                linalg.initialize_lapack()
                _PREPARED.append(True)
            except Exception:  # another JAX: traces only
                _PREPARED.append(False)
    return _PREPARED[0]


_PROCESSOR: list[str] = []


def _processor() -> str:
    """This machine's processor: its model name and instruction-set flags (``/proc/cpuinfo``),
    else what ``platform`` says."""
    if not _PROCESSOR:
        import platform

        text = platform.machine() + "|" + platform.processor()
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
                seen = {}
                for line in fh:
                    name, _, value = line.partition(":")
                    name = name.strip()
                    if name in ("model name", "flags", "Features", "CPU part") and name not in seen:
                        seen[name] = value.strip()
                    if line.strip() == "":
                        break  # the first processor's block
            text += "|" + "|".join(f"{k}={v}" for k, v in sorted(seen.items()))
        except OSError:
            pass
        _PROCESSOR.append(text)
    return _PROCESSOR[0]


def _executable(store: Path, key: str, args, traced: Callable[[], Callable], kernels: bool = True) -> Callable:
    """The function ``key`` at ``args`` as this machine's executable: loaded from the store, or
    compiled from ``traced()`` (the stored trace, or a fresh one) and stored. Where executables
    are not kept, or this one cannot be compiled, loaded or run, ``jax.jit(traced())``: JAX
    compiles it at the first call (from its persistent cache where it can)."""
    import jax

    path = _executable_path(store, key, args, kernels)
    if path is None:
        return jax.jit(traced())
    loaded = _read_executable(path)
    if loaded is None:
        target = traced()
        if not _write_executable(path, target, args, kernels):
            return jax.jit(target)
        loaded = _read_executable(path)  # what later processes will load: run it here first
        if loaded is None:
            return jax.jit(target)
    return _FirstCallChecked(loaded, path, lambda: jax.jit(traced()))


def _read_executable(path: Path) -> Callable | None:
    if not path.is_file():
        return None
    try:
        import pickle

        from jax.experimental import serialize_executable

        payload, in_tree, out_tree = pickle.loads(path.read_bytes())
        return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # unreadable, or from another jaxlib: compiled afresh and stored again
        return None


def _write_executable(path: Path, target: Callable, args, kernels: bool = True) -> bool:
    """Compile ``target`` for ``args`` afresh and store the executable; False where it fails.
    Afresh, not from JAX's persistent cache: an executable loaded from there serialises without
    its kernels (jaxlib 0.10 on the CPU: "Function ... not found" when run), so it is compiled
    under a name of its own (the cache's key hashes the module, whose name it carries) and not
    written to that cache (the executable is stored here instead)."""
    import math
    import pickle
    import uuid

    import jax
    from jax.experimental import serialize_executable

    def fresh(*a):
        return target(*a)

    fresh.__name__ = fresh.__qualname__ = f"lensfit_{uuid.uuid4().hex}"
    try:
        from jax._src import config as jax_config

        with jax_config.persistent_cache_min_compile_time_secs(math.inf):
            lowered = jax.jit(fresh).lower(*args)
            if not kernels and "lapack" in lowered.as_text().lower():
                return False  # it does call them: not kept, so never loaded unprepared
            compiled = lowered.compile()
        _store(path, pickle.dumps(serialize_executable.serialize(compiled)))
        return True
    except Exception:  # not compilable ahead of time, not serialisable, a read-only store, ...
        return False


class _FirstCallChecked:
    """A loaded executable whose first call is awaited: if it fails (an executable that does
    not run here), the stored file is removed and ``fallback()`` (jit) answers instead."""

    def __init__(self, loaded: Callable, path: Path, fallback: Callable[[], Callable]):
        self.loaded, self.path, self.fallback = loaded, path, fallback
        self.checked = False

    def __call__(self, *args):
        if self.checked:
            return self.loaded(*args)
        import jax

        try:
            out = jax.block_until_ready(self.loaded(*args))
        except Exception:
            try:
                self.path.unlink()
            except OSError:
                pass
            self.loaded = self.fallback()
            out = self.loaded(*args)
        self.checked = True
        return out


_JITTED: dict[tuple, Callable] = {}


def _jitted(fn: Callable, static: dict[str, Any]) -> Callable:
    k = (fn, tuple(sorted(static.items())))
    if k not in _JITTED:
        _JITTED[k] = jax_jit(fn, static)
    return _JITTED[k]


def _load_or_export(path: Path, fn: Callable, args, static: dict[str, Any]) -> Callable:
    """The function to compile: the stored trace's ``call``, or ``fn`` traced, exported and
    stored (``fn`` with ``static`` bound where that fails)."""
    from jax import export

    try:
        exported = export.deserialize(bytearray(path.read_bytes()))
        return exported.call
    except Exception:  # missing, unreadable or from another JAX: trace afresh below
        pass
    try:
        exported = _export(fn, args, static)
        _store(path, exported.serialize())
        return exported.call
    except Exception:  # no serialization support (flatbuffers missing), read-only store, ...
        return partial(fn, **static)


def _store(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a concurrent process (or thread) reads the old file
    or the new one, never a part."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.partial")
    tmp.write_bytes(data)
    os.replace(tmp, path)
