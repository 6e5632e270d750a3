"""Sharpening halos on a stack's edge profiles: the test behind ``lensfit.measurement.processing``.

A lens's point spread function is never negative, so the edge it blurs rises monotonically from
one level to the other, whatever the aberrations. Sharpening (an unsharp mask, a deconvolution)
subtracts a blurred copy: a dark undershoot before the edge and a bright overshoot after it,
which no optics make. Each profile is fitted with the uniform disk through an unsharp mask,
``f + a (f - g * f)`` (``g`` a Gaussian of ``HALO_SIGMA_PX``, ``f`` the pixel-integrated disk
edge), and the amounts ``a`` are pooled over the stack: about 0 for an image as the lens drew
it, 0.3-1 for a camera's or a raw developer's default sharpening. The amount is also what the
blur readings lose: the fit's disk comes out smaller by about that share of a pixel."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.estimators.edge_model import squared_radius
from lensfit.measurement.psf import pixel_edge_profile

#: The unsharp mask's Gaussian (1 sigma, px) the test fits with: in-camera and raw developers'
#: defaults run 0.5-2 px, and the amount a mask of another radius reads differs little in sign.
HALO_SIGMA_PX = 1.0
#: Profiles per compiled call and bins per profile (padded).
_CHUNK = 32
_NPIX = 256
_GRID = 256


def _model(theta, d, nx, ny):
    # The edge on a regular grid that reaches 4 sigma beyond the profile's bins, blurred by the
    # Gaussian as a matrix over that grid, both read at the bins (one evaluation of the edge).
    d0, rho, lo, hi, a = (theta[i] for i in range(5))
    radius = jnp.sqrt(squared_radius(rho) + 1e-12)  # (as the edge estimator's model)
    reach = 4.0 * HALO_SIGMA_PX
    grid = jnp.linspace(jnp.min(d) - reach, jnp.max(d) + reach, _GRID)
    f = lo + (hi - lo) * pixel_edge_profile(grid - d0, radius, nx, ny)
    kernel = jnp.exp(-0.5 * ((grid[:, None] - grid[None, :]) / HALO_SIGMA_PX) ** 2)
    blurred = (kernel @ f) / jnp.sum(kernel, axis=1)
    return jnp.interp(d, grid, f + a * (f - blurred))


def _residuals(theta, args):
    d, v, w, nx, ny = args
    return w * (v - _model(theta, d, nx, ny))


@jax.jit
def _fit_chunk(theta0, d, v, w, nx, ny):
    from lensfit.fitting import lm

    def one(t0, d, v, w, nx, ny):
        args = (d, v, w, nx, ny)
        theta, cost, ok = lm.least_squares(_residuals, t0, args, max_steps=40, rtol=1e-8, atol=1e-10, ftol=1e-6)
        _, J = lm.residuals_and_jacobian(_residuals, theta, args)
        dof = jnp.maximum(jnp.sum(w > 0).astype(cost.dtype) - 5.0, 1.0)
        var = jnp.maximum(cost / dof, 1.0) * lm.covariance(J)[4, 4]
        return theta[4], var, ok & jnp.isfinite(cost)

    return jax.vmap(one)(theta0, d, v, w, nx, ny)


def halo_amounts(profiles: list[tuple], radii: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """The unsharp-mask amount of each profile ``(d, s, values, standard errors, normal)`` (the edge
    estimator's, ``lensfit.estimators.edge``) and its variance; ``radii``: each one's blur radius
    from the first pass (px), the fit's start. Profiles too short to show a halo give NaN."""
    n = len(profiles)
    size = _CHUNK * max(1, math.ceil(n / _CHUNK))
    D = np.tile(np.linspace(-4.0, 4.0, _NPIX), (size, 1))
    V, W = np.zeros((size, _NPIX)), np.zeros((size, _NPIX))
    NX, NY = np.ones(size), np.zeros(size)
    T = np.tile([0.0, 1.0, 0.0, 1.0, 0.0], (size, 1))
    usable = np.zeros(size, bool)
    for i, ((d, _s, v, se, nrm), r) in enumerate(zip(profiles, radii)):
        d, v, se = (np.asarray(x, np.float64)[:_NPIX] for x in (d, v, se))
        if len(d) < 16 or r is None or not math.isfinite(r):
            continue
        D[i, :len(d)], V[i, :len(d)], W[i, :len(d)] = d, v, 1.0 / se
        D[i, len(d):] = d[-1]
        NX[i], NY[i] = nrm
        low, high = np.mean(v[d < d.min() / 2]), np.mean(v[d > d.max() / 2])
        T[i] = [0.0, r * r, low, high, 0.0]
        usable[i] = True
    amount, var = np.full(size, np.nan), np.full(size, np.nan)
    with jax.enable_x64(True):
        for k in range(0, size, _CHUNK):
            part = slice(k, k + _CHUNK)
            a, va, ok = (np.asarray(x) for x in _fit_chunk(T[part], D[part], V[part], W[part], NX[part], NY[part]))
            good = ok & np.isfinite(a) & np.isfinite(va) & (va > 0)
            amount[part] = np.where(good, a, np.nan)
            var[part] = np.where(good, va, np.nan)
    amount[~usable], var[~usable] = np.nan, np.nan
    return amount[:n], var[:n]


def pooled(amount: np.ndarray, var: np.ndarray) -> tuple[float, float, int]:
    """The stack's amount (the median of the edges'), its standard error (from their scatter:
    1.25 MAD / sqrt n, robust to a few edges the disk fits badly) and the number of edges."""
    a = amount[np.isfinite(amount) & np.isfinite(var)]
    if a.size < 5:
        return math.nan, math.nan, int(a.size)
    med = float(np.median(a))
    return med, float(1.4826 * np.median(np.abs(a - med)) * 1.2533 / math.sqrt(a.size)), int(a.size)
