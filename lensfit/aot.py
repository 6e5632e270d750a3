"""Traced once per installation: JAX functions exported (``jax.export``) and kept on disk.

Tracing a batched solver with closed-form pixel profiles takes seconds, in every new process
(the persistent compilation cache keeps compiled code, not traces). A function wrapped here is
traced and exported at its first use with a given argument shape and stored beside the
compilation cache; later processes deserialize it (milliseconds) and compile it from the
persistent cache. Only where the command-line tools switched the cache on
(:func:`lensfit.jaxcache.enable_compilation_cache`); otherwise, and on any failure to read or
write the store, the plain ``jax.jit`` path runs (same results). The file name carries the JAX
version, the backend and a hash of the source of the modules the function depends on, so a
change of any of them traces afresh.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import threading
from functools import partial
from pathlib import Path
from typing import Any, Callable

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
         modules: tuple[str, ...] = ()) -> Any:
    """``fn(*args, **static)`` through the store (see the module docstring). ``fn`` must be pure
    and its result a pytree of arrays; ``modules``: the names of the modules whose source defines
    it (their change invalidates the stored trace)."""
    static = static or {}
    store = _DIR[0]
    if store is None:
        return _jitted(fn, static)(*args)
    key = _key(name, args, static, modules)
    runner = _LOADED.get(key)
    if runner is None:
        with _LOCK:
            lock = _KEY_LOCKS.setdefault(key, threading.Lock())
        with lock:  # one thread loads a function (lensfit.measure loads in the background), others wait
            runner = _LOADED.get(key)
            if runner is None:
                runner = _load_or_export(store / f"{key}.jaxexport", fn, args, static)
                _LOADED[key] = runner
    return runner(*args)


_JITTED: dict[tuple, Callable] = {}


def _jitted(fn: Callable, static: dict[str, Any]) -> Callable:
    k = (fn, tuple(sorted(static.items())))
    if k not in _JITTED:
        _JITTED[k] = jax_jit(fn, static)
    return _JITTED[k]


def _load_or_export(path: Path, fn: Callable, args, static: dict[str, Any]) -> Callable:
    import jax
    from jax import export

    try:
        exported = export.deserialize(bytearray(path.read_bytes()))
        return jax.jit(exported.call)
    except Exception:  # missing, unreadable or from another JAX: trace afresh below
        pass
    try:
        exported = _export(fn, args, static)
        data = exported.serialize()
        tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
        tmp.write_bytes(data)
        os.replace(tmp, path)  # atomic: a concurrent process reads the old file or the new one
        return jax.jit(exported.call)
    except Exception:  # no serialization support (flatbuffers missing), read-only store, ...
        return _jitted(fn, static)
