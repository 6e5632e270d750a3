"""Argument checks and the numeric namespace of the optics API.

The public optics functions accept Python scalars, NumPy or JAX arrays. With NumPy or Python
inputs they compute in NumPy float64 and return NumPy values, without importing JAX (so that
``lensfit dof`` starts in a fraction of a second); with a JAX array among the inputs they
compute in ``jax.numpy`` (float64 switched on for the duration of the call only, never as a
side effect of importing the library; a call inside a caller's trace keeps the caller's
setting) and can be traced, jitted and differentiated. With concrete inputs they validate
every element and raise :class:`lensfit.errors.InputError` naming the argument; inside a
caller's ``jax.jit`` trace values are abstract, so the checks are skipped and the documented
valid range is the caller's responsibility.
"""

from __future__ import annotations

import contextlib
import functools
import sys
from typing import Any, Callable, TypeVar

import numpy as np

from lensfit.errors import InputError

F = TypeVar("F", bound=Callable[..., Any])


def namespace(*values: Any) -> Any:
    """The array namespace of a computation on ``values``: ``jax.numpy`` where any of them is a JAX
    array or tracer, else ``numpy`` (Python numbers included).

    The library's one array-backend rule: code that runs on NumPy and JAX alike takes its
    namespace from its inputs with this function, never from an argument or a setting."""
    if any(_jax_array(v) for v in values):
        import jax.numpy as jnp

        return jnp
    return np


def _jax_array(x: Any) -> bool:
    jax = sys.modules.get("jax")  # not imported: no JAX array can exist
    return jax is not None and isinstance(x, (jax.Array, jax.core.Tracer))


def _is_traced(x: Any) -> bool:
    jax = sys.modules.get("jax")
    return jax is not None and isinstance(x, jax.core.Tracer)


def _numeric(x: Any) -> bool:
    return isinstance(x, (int, float, np.ndarray, np.generic)) and not isinstance(x, bool)


def float64(fn: F) -> F:
    """Run ``fn`` in float64: NumPy for NumPy/Python inputs; for JAX inputs ``jax.numpy`` with
    64-bit types (unless called inside a trace), every numeric input a JAX array, so that the
    body's :func:`namespace` of any input is the call's."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if namespace(*args, *kwargs.values()) is np:
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                return fn(*args, **kwargs)
        import jax
        import jax.numpy as jnp

        traced = any(_is_traced(a) for a in (*args, *kwargs.values()))
        with contextlib.nullcontext() if traced else jax.enable_x64(True):
            dtype = jnp.float64 if jax.config.jax_enable_x64 else None
            args = [jnp.asarray(a, dtype) if _numeric(a) else a for a in args]
            kwargs = {k: jnp.asarray(a, dtype) if _numeric(a) else a for k, a in kwargs.items()}
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def arg(
    name: str,
    value: Any,
    *,
    positive: bool = False,
    nonnegative: bool = False,
    allow_inf: bool = False,
) -> Any:
    """Validate a numeric argument and return it as a float64 array of the call's namespace.

    Rules checked on concrete values: finite (or +inf where ``allow_inf``), never NaN,
    and ``> 0`` (``positive``) or ``>= 0`` (``nonnegative``).
    """
    if not _is_traced(value):
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(name, value, "a number or an array of numbers") from None
        if a.size:
            if np.isnan(a).any():
                raise InputError(name, float("nan"), "a number (not NaN)")
            inf_ok = "> 0 (inf allowed)" if positive else ">= 0 (inf allowed)" if nonnegative else "finite or +inf"
            bad_inf = np.isneginf(a) | (np.isposinf(a) & (not allow_inf))
            if bad_inf.any():
                req = inf_ok if allow_inf else ("> 0 and finite" if positive else ">= 0 and finite" if nonnegative else "finite")
                raise InputError(name, float(a[bad_inf].flat[0]), req)
            if positive and (a <= 0).any():
                raise InputError(name, float(a[a <= 0].flat[0]), "> 0" + (" (inf allowed)" if allow_inf else ""))
            if nonnegative and (a < 0).any():
                raise InputError(name, float(a[a < 0].flat[0]), ">= 0" + (" (inf allowed)" if allow_inf else ""))
    if namespace(value) is np:
        return np.asarray(value, dtype=np.float64)
    import jax
    import jax.numpy as jnp

    return jnp.asarray(value, dtype=jnp.float64 if jax.config.jax_enable_x64 else None)


def require(ok: Any, name: str, value: Any, requirement: str, hint: str = "") -> None:
    """Raise :class:`InputError` where the elementwise condition ``ok`` fails (concrete values only)."""
    if _is_traced(ok) or _is_traced(value):
        return
    ok_np = np.asarray(ok, dtype=bool)
    if not ok_np.all():
        v = np.broadcast_to(np.asarray(value, dtype=np.float64), ok_np.shape)
        raise InputError(name, float(v[~ok_np].flat[0]), requirement, hint)
