"""Defocus point-spread models and their edge profiles (JAX, float64 by the caller's scope).

A thin lens spreads an out-of-focus point into a uniform disk of diameter c (radius R = c/2).
Its edge-spread function (ESF, the fraction of the disk left of a line at signed distance t
from the centre), with x = t/R clipped to [-1, 1]::

    ESF(x) = 1/2 + (x sqrt(1 - x^2) + asin x) / pi

and its antiderivative (used to average exactly over a pixel's extent)::

    G(x) = x/2 + (x asin x + sqrt(1 - x^2) - (1 - x^2)^(3/2) / 3) / pi   for |x| <= 1,
    G(x) = 0 for x <= -1,   G(x) = x for x >= 1.

and its second antiderivative::

    H(x) = x^2/4 + 1/16 + ((4 x^2 + 1)/8 asin x + 5/8 x sqrt(1 - x^2)
                           - x (1 - x^2)^(3/2) / 12) / pi                  for |x| <= 1,
    H(x) = 0 for x <= -1,   H(x) = x^2/2 + 1/8 for x >= 1.

A pixel (square, side 1, 100 % fill) at signed normal distance d from the edge sees the ESF
averaged over the pixel's projection on the edge normal n = (n_x, n_y), which is the
convolution of two boxes of widths a = |n_x| and b = |n_y|; the average is therefore exact in
closed form: (1/ab) [H(d+a/2+b/2) - H(d+a/2-b/2) - H(d-a/2+b/2) + H(d-a/2-b/2)] (in units of
the radius), and (1/a) [G(d+a/2) - G(d-a/2)] when b is negligible.

Reference: the ESF of a uniform disk is the integral of its semicircular line-spread
function, e.g. Smith, *Modern Optical Engineering*, 4th ed., sec. 11.9.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.optics.checks import namespace


def disk_esf(x):
    """Edge-spread function of the unit disk at x = t/R (any real x)."""
    xc = jnp.clip(x, -1.0, 1.0)
    return 0.5 + (xc * jnp.sqrt(1.0 - xc * xc) + jnp.arcsin(xc)) / jnp.pi


def _antiderivative(core, above, derivative, doc: str):
    """A closed-form antiderivative of an edge-spread function of the unit disk: ``core(x)`` for
    |x| < 1, ``above(x)`` for x >= 1, 0 below -1; its derivative given explicitly (``derivative``,
    called lazily), so that gradients stay exact and finite at |x| = 1."""

    @jax.custom_jvp
    def f(x):
        inside = jnp.abs(x) < 1.0
        xs = jnp.where(inside, x, 0.0)
        return jnp.where(inside, core(xs), jnp.where(x >= 1.0, above(x), 0.0))

    @f.defjvp
    def _jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        return f(x), derivative()(x) * dx

    f.__doc__ = doc
    return f


def _disk_g(xs):
    one_minus = 1.0 - xs * xs
    return 0.5 * xs + (xs * jnp.arcsin(xs) + jnp.sqrt(one_minus) - one_minus * jnp.sqrt(one_minus) / 3.0) / jnp.pi


def _disk_h(xs):
    xp = namespace(xs)
    x2 = xs * xs
    root = xp.sqrt(1.0 - x2)
    return (0.25 * x2 + 1.0 / 16.0
            + ((4.0 * x2 + 1.0) / 8.0 * xp.arcsin(xs) + 0.625 * xs * root - xs * (1.0 - x2) * root / 12.0) / xp.pi)


disk_esf_integral = _antiderivative(_disk_g, lambda x: x, lambda: disk_esf,
                                    "G(x): antiderivative of :func:`disk_esf` with G(-inf) = 0 (exact, see module "
                                    "docstring).")
disk_esf_integral2 = _antiderivative(_disk_h, lambda x: 0.5 * x * x + 0.125, lambda: disk_esf_integral,
                                     "H(x): second antiderivative of :func:`disk_esf`, H(-inf) = 0 (exact, see the "
                                     "module docstring).")


def pixel_edge_profile(d, radius_px, nx, ny):
    """Mean over a unit pixel of a disk-blurred step rising towards +d (exact, closed form).

    Parameters
    ----------
    d : array
        Signed distance (px) of each pixel centre from the edge line, along the normal.
    radius_px : scalar
        Blur-disk radius R = c/2 in pixels (>= 0; 0 gives a sharp step).
    nx, ny : scalars
        Components of the edge normal in image coordinates (unit vector).

    Returns
    -------
    array, values in [0, 1]: 0 far on the -d side, 1 far on the +d side.
    """
    R = jnp.maximum(jnp.abs(radius_px), 1e-6)
    a = jnp.maximum(jnp.abs(nx), jnp.abs(ny))
    b = jnp.minimum(jnp.abs(nx), jnp.abs(ny))
    thin = b < 1e-3
    b_safe = jnp.where(thin, 1.0, b)

    def H(t):
        return R * R * disk_esf_integral2(t / R)

    def G(t):
        return R * disk_esf_integral(t / R)

    two_box = (H(d + 0.5 * (a + b_safe)) - H(d + 0.5 * (a - b_safe)) - H(d - 0.5 * (a - b_safe))
               + H(d - 0.5 * (a + b_safe))) / (a * b_safe)
    one_box = (G(d + 0.5 * a) - G(d - 0.5 * a)) / a
    return jnp.where(thin, one_box, two_box)


def pixel_edge_profiles_np(d, radii, boxes) -> np.ndarray:
    """:func:`pixel_edge_profile` in NumPy for many radii at once, ``(len(d), len(radii))``;
    ``boxes``: the two box widths (|n_x|, |n_y|, or a footprint widened as
    ``lensfit.estimators.profile.footprint`` does), the narrower held at 1e-3 or more. For callers
    that evaluate a few profiles per edge outside a compiled fit, where JAX's dispatch would cost
    more than the arithmetic."""
    R = np.maximum(np.asarray(radii, np.float64), 1e-6)[None, :]

    def H(t):
        x = t / R
        inside = np.abs(x) < 1.0
        core = _disk_h(np.where(inside, x, 0.0))
        return R * R * np.where(inside, core, np.where(x >= 1.0, 0.5 * x * x + 0.125, 0.0))

    return over_pixel_boxes(H, np.asarray(d, np.float64)[:, None], boxes)


def over_pixel_boxes(H, d, boxes) -> np.ndarray:
    """The mean over the pixel footprint ``boxes`` (two box widths, the narrower held at 1e-3 or
    more) at ``d`` of a profile whose second antiderivative is ``H``: the two boxes' convolution
    in closed form, from H at the footprint's four corners."""
    a, b = max(abs(boxes[0]), abs(boxes[1])), max(min(abs(boxes[0]), abs(boxes[1])), 1e-3)
    return (H(d + 0.5 * (a + b)) - H(d + 0.5 * (a - b)) - H(d - 0.5 * (a - b)) + H(d - 0.5 * (a + b))) / (a * b)


def disk_kernel(diameter: float, oversample: int = 8) -> np.ndarray:
    """Area-weighted uniform disk of ``diameter`` cells, centred on the middle cell, unit sum.

    Each cell's weight is the fraction of ``oversample**2`` sub-points inside the disk; a disk
    smaller than one cell degenerates to the single centre cell (a delta).
    """
    r = 0.5 * diameter
    half = int(math.ceil(r + 0.5))
    n = 2 * half + 1
    sub = (np.arange(oversample) + 0.5) / oversample - 0.5
    fine = (np.arange(-half, half + 1)[:, None] + sub[None, :]).ravel()
    k = np.empty((n, n))
    block = max(1, (1 << 22) // (n * oversample * oversample))  # cell rows per step: memory O(n), not O(n^2)
    for i0 in range(0, n, block):
        rows = fine[i0 * oversample:(i0 + block) * oversample]
        inside = (rows[:, None] ** 2 + fine[None, :] ** 2) <= r * r
        k[i0:i0 + block] = inside.reshape(-1, oversample, n, oversample).mean(axis=(1, 3))
    if k.sum() == 0:
        k[half, half] = 1.0
    return (k / k.sum()).astype(np.float64)
