"""The edge estimator's model of an edge profile and the start of its fit (``lensfit.estimators.edge``
describes the method): the uniform disk or two concentric disks, integrated over square pixels
in closed form, convolved where diffraction is modelled with the edge's Airy kernel
(``lensfit.measurement.diffraction.edge_kernel``); the residuals the batched Levenberg-Marquardt solve
minimises and the grids it starts from. Pure JAX functions of one edge: the estimator maps
them over chunks of edges (packed by :func:`chunks`) and compiles them once (``lensfit.runtime.jaxcache``)."""

from __future__ import annotations

import math
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.measurement.diffraction import KERNEL_KNOTS, edge_kernel
from lensfit.measurement.psf import disk_esf_integral2, pixel_edge_profile
from lensfit.optics.checks import namespace

RADIUS_GRID = np.geomspace(0.05, 200.0, 24)
#: Where diffraction is modelled, the start's grid over the radius, as shares of the uniform
#: disk's reading of the same edge.
AIRY_START_SHARES = (0.02, 0.25, 0.45, 0.6, 0.72, 0.82, 0.91, 1.0)
#: Prior 1 sigma of the diffraction fit's ramp, per px as a share of the edge's contrast: the
#: Airy tails of a neighbouring edge 8-16 px away slope the window by about 1e-3 of the
#: contrast per px; held near that, the ramp does not trade with a small blur.
RAMP_PRIOR = 2e-3
RHO_SMOOTH_PX2 = 1e-6  # smoothing of R^2 >= 0 at 0 (px^2); see squared_radius
#: Prior 1 sigma of the inner disk's share of the light, a (about 0), and of logit t, the inner
#: radius over the outer one (about 0: t = 1/2); weak, they hold the shape where the blur is too
#: small to show one.
SHARE_PRIOR = 1.0
RATIO_PRIOR = 2.0
#: Candidate starts of the two-disk fit (a, logit t): cores in a halo (a > 0), bright rims
#: (a < 0, within the centre's intensity >= 0, a >= -t^2 / (1 - t^2)) and, last, the uniform disk
#: itself (a = 0), which the two-disk family holds: started no worse than the disk's own reading,
#: the two-disk fit never ends worse than it (Levenberg-Marquardt never raises the cost).
SHAPE_GRID = ((0.3, -0.5), (0.6, -0.5), (0.3, 0.5), (0.6, -1.5), (0.8, 0.0),
              (-0.5, 1.5), (-0.3, 0.5), (-1.0, 1.5), (-0.2, 0.0), (0.0, 0.0))
#: Smallest share of the outer disk's variance the two disks may keep, ``m = 1 - a (1 - t^2)``:
#: below it the outer ring's light is negative beyond reason, and the reading is no reading.
MIN_VARIANCE_SHARE = 0.05


def squared_radius(rho):
    """R^2 from the solver's parameter: a smooth max(rho, 0) (within 1e-12 px^2 of rho for a blur
    over 0.01 px). A sharp edge has its least-squares minimum at R = 0; ``|rho|`` would put a
    kink there, on which the solver bounces instead of settling."""
    return 0.5 * (rho + namespace(rho).sqrt(rho * rho + RHO_SMOOTH_PX2**2))


def squared_radius_slope(rho: float) -> float:
    """d R^2 / d rho of :func:`squared_radius`."""
    return 0.5 * (1.0 + rho / math.hypot(rho, RHO_SMOOTH_PX2))


def profile(x, radius, nx, ny, airy):
    """The pixel-integrated disk ESF; where diffraction is modelled (``airy``: the edge's kernel
    ``(knots, slope changes, tail)`` from ``lensfit.measurement.diffraction.edge_kernel``, which holds the
    pixel's footprint too; None: no diffraction), the disk ESF convolved with that piecewise-linear
    kernel, exactly: one second antiderivative of the disk's ESF per knot."""
    if airy is None:
        return pixel_edge_profile(x, radius, nx, ny)
    knots, changes, tail = airy
    R = jnp.maximum(jnp.abs(radius), 1e-6)
    return tail + (R * R * disk_esf_integral2((x[..., None] - knots) / R)) @ changes


def model(theta, d, s, nx, ny, shaped: bool, airy=None):
    # theta = (d0, rho = R^2, lo, hi, turn[, a, u]): the squared radius keeps the model smooth and
    # well-conditioned as the blur vanishes (the profile depends on R only to second order
    # there); `turn` rotates the edge line (radians) about the window's middle, so that the
    # line's own uncertainty is part of the covariance; when shaped, `a` is the inner disk's
    # share of the light and t = sigmoid(u) its radius over R (a = 0: the uniform disk).
    d0, rho, lo, hi, turn = (theta[i] for i in range(5))
    R = jnp.sqrt(squared_radius(rho) + 1e-12)
    x = d - d0 - turn * s
    outer = profile(x, R, nx, ny, airy)
    if not shaped:
        if airy is not None:
            # A ramp across the window: the Airy tails (1/x^2) of the target's neighbouring edges
            # reach into it, a slope the levels alone cannot follow (unmodelled, an edge 8-16 px
            # away biased a 2-6 px reading 1-10 % low).
            return lo + (hi - lo) * outer + theta[5] * x
        return lo + (hi - lo) * outer
    a, u = theta[5], theta[6]
    inner = profile(x, R * jax.nn.sigmoid(u), nx, ny, airy)
    return lo + (hi - lo) * (outer + a * (inner - outer))


class Profile(NamedTuple):
    """One edge's binned profile as its fit takes it (a pytree): each bin's offset across the
    edge ``d`` and position along it ``s`` (px), its mean value ``v`` and weight ``w`` (1 / the
    standard error of the mean; 0 for padding), the edge normal's components ``nx``, ``ny``, and
    the edge's Airy kernel where diffraction is modelled (None: not)."""

    d: Any
    s: Any
    v: Any
    w: Any
    nx: Any
    ny: Any
    airy: Any = None


def residuals(theta, args: Profile, shaped: bool):
    d, s, v, w, nx, ny, airy = args
    r = w * (v - model(theta, d, s, nx, ny, shaped, airy))
    if not shaped:
        if airy is not None:  # the ramp, held near 0 where the profile does not ask for one
            return jnp.concatenate([r, (theta[5] / (RAMP_PRIOR * jnp.abs(theta[3] - theta[2]) + 1e-12))[None]])
        return r
    # The shape has weak priors that hold it where the blur is too small to show one.
    return jnp.concatenate([r, jnp.stack([theta[5] / SHARE_PRIOR, theta[6] / RATIO_PRIOR])])


def grid_start(d, s, v, w, nx, ny, airy=None, radii=None):
    """Best radius on a grid (``RADIUS_GRID``, or ``radii``), with the two levels solved by
    weighted linear least squares (the 2 x 2 normal equations in closed form); the edge at d = 0,
    where the profile put the line it found in the image (a grid over the offset as well would
    move the estimates by under 0.002 % for a third more of the solve)."""
    radii = jnp.asarray(RADIUS_GRID) if radii is None else radii
    w2 = w * w

    def rss(radius):
        p = profile(d, radius, nx, ny, airy)
        q = 1.0 - p
        # Normal equations of v = lo q + hi p with weights w^2.
        a11, a12, a22 = jnp.sum(w2 * q * q), jnp.sum(w2 * q * p), jnp.sum(w2 * p * p)
        b1, b2 = jnp.sum(w2 * q * v), jnp.sum(w2 * p * v)
        det = a11 * a22 - a12 * a12
        ok = det > 1e-12 * (a11 * a22 + 1e-300)
        det = jnp.where(ok, det, 1.0)
        lo = jnp.where(ok, (a22 * b1 - a12 * b2) / det, 0.0)
        hi = jnp.where(ok, (a11 * b2 - a12 * b1) / det, 0.0)
        r = w * (v - lo * q - hi * p)
        return jnp.where(ok, jnp.sum(r * r), jnp.inf), jnp.stack([lo, hi])

    costs, coefs = jax.vmap(rss)(radii)
    k = jnp.argmin(costs)
    return jnp.stack([0.0, radii[k] ** 2, coefs[k][0], coefs[k][1], 0.0])


def variance_share(a, u):
    """``m = 1 - a (1 - t^2)``, t = sigmoid(u): the two disks' variance over the outer one's."""
    t = jax.nn.sigmoid(u)
    return 1.0 - a * (1.0 - t * t)


def to_moment(theta):
    """The two-disk fit's parameters with R^2 replaced by the spot's second moment, ``m R^2`` (a
    quarter of the squared second-moment diameter, the quantity the reading reports)."""
    return theta.at[1].set(theta[1] * variance_share(theta[5], theta[6]))


def from_moment(p):
    """Inverse of :func:`to_moment` (m floored at ``MIN_VARIANCE_SHARE``)."""
    return p.at[1].set(p[1] / jnp.maximum(variance_share(p[5], p[6]), MIN_VARIANCE_SHARE))


def moment_residuals(p, args):
    """:func:`residuals` of two disks in the parameters of :func:`to_moment`. The data fix the
    spot's second moment far better than how it splits between the radius and the shape; in R^2
    that well-fixed direction runs diagonally through (R^2, a, t), and the solver crept along it
    (on the demo stack enlarged 1.25x, 30 of 217 fits still moving after 40 steps, 13 readings
    more than 1 % off their minimum, six collapsed to 0); with the moment a parameter of its own,
    (a, t) move at a fixed moment."""
    return residuals(from_moment(p), args, shaped=True)


def shape_start(theta_disk, args):
    """The two-disk start: on a grid of shapes (a, logit t) around the uniform disk's solution,
    each with the outer radius that keeps the disk's second moment, the one of least cost."""
    fn = partial(residuals, shaped=True)
    rho_disk = squared_radius(theta_disk[1])
    starts = []
    for a, u in SHAPE_GRID:
        t = 1.0 / (1.0 + math.exp(-u))
        m = 1.0 - a * (1.0 - t * t)
        starts.append(jnp.concatenate([theta_disk[:1], jnp.stack([rho_disk / m]), theta_disk[2:5], jnp.array([a, u])]))
    starts = jnp.stack(starts)
    costs = jax.vmap(lambda th: jnp.sum(fn(th, args) ** 2))(starts)
    return starts[jnp.argmin(costs)]


def chunks(npix: int, size: int, samples: list, disk: list | None, airy: list[float] | None) -> list[tuple]:
    """The arrays of the estimator's batched fit (``lensfit.estimators.edge``) for ``samples``
    (d, s, values, standard errors, normal) padded to ``npix`` bins, in chunks of ``size``
    problems (padding rows: a harmless dummy problem with zero weights); ``disk``: each one's
    uniform-disk solution to start from, ``airy``: each one's Airy scale in px (or None)."""
    n = size * math.ceil(len(samples) / size)
    D = np.tile(np.linspace(-4.0, 4.0, npix), (n, 1))
    V, S, W = np.zeros((n, npix)), np.zeros((n, npix)), np.zeros((n, npix))
    NX, NY = np.ones(n), np.zeros(n)
    T = np.tile([0.0, 1.0, 0.0, 1.0, 0.0], (n, 1))
    knots, changes, tails = np.zeros((n, KERNEL_KNOTS)), np.zeros((n, KERNEL_KNOTS)), np.zeros(n)
    if airy is None:  # dummies: the compiled fit without diffraction never reads them
        knots, changes = knots[:, :1], changes[:, :1]
    else:  # the edges' kernels at once, 256 at a time (a peak of about 66 MB)
        normals = np.array([nrm for *_, nrm in samples], np.float64).reshape(-1, 2)
        scales = np.asarray(airy, np.float64)
        for k in range(0, len(samples), 256):
            part = slice(k, min(k + 256, len(samples)))
            knots[part], changes[part], tails[part] = edge_kernel(scales[part], normals[part, 0], normals[part, 1])
    for i, theta in enumerate(disk or []):
        T[i] = theta[:5]
    for i, (d, s_along, v, se, nrm) in enumerate(samples):
        D[i, :len(d)], S[i, :len(d)], V[i, :len(d)], W[i, :len(d)] = d, s_along, v, 1.0 / se
        NX[i], NY[i] = nrm
    arrays = (D, S, V, W, NX, NY, T, (knots, changes, tails))
    return [jax.tree_util.tree_map(lambda x: x[k:k + size], arrays) for k in range(0, n, size)]
