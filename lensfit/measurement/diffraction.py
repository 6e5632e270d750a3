"""Diffraction in the blur reading: the Airy pattern's line-spread function, as a kernel per edge.

A lens stopped down far enough is diffraction-limited: the defocus disk is convolved with the
Airy pattern of the exit pupil, whose scale is ``a = lambda N_w / p`` pixels (``N_w`` the working,
image-side f-number, ``S / A`` for any lens: the pinhole distance over the entrance-pupil
diameter; first dark ring at ``1.22 a``). Its line-spread function (LSF) falls off only as
``1 / x^2``, so its variance is unbounded and no floor added in quadrature describes it: a
uniform-disk fit to an edge blurred by a disk of ``c`` px and an Airy pattern of ``a = 1.5 px``
reads 3.1 px at ``c = 0`` and ``c + 1.2 px`` at ``c = 24`` (the excess grows with the window the
blur asks for), which leaves the f-number several per cent off (docs/src/explanation/lens-models.md, "Diffraction").

The edge estimator therefore convolves its model profile with the Airy LSF where the caller
gives ``a``. Per edge, the kernel that does not change while the edge is fitted -- the Airy LSF
convolved with the pixel's footprint across the edge (two boxes of widths ``|n_x|`` and
``|n_y|``) -- is tabulated on the host at fixed knots (:func:`edge_kernel`: 49 evenly over the
core, ``3 a`` plus the footprint either side, 24 a side growing geometrically out to ``40 a`` or
32 px, whichever is further;
values corrected for the linear interpolant's curvature error, ``K_j - h^2 K''_j / 12``) and
interpolated linearly between them. A piecewise-linear kernel convolved with the uniform disk's
ESF is exact in closed form: ``sum_j c_j R^2 H((x - xi_j) / R)``, ``c_j`` the kernel's change of
slope at knot ``xi_j`` and ``H`` the disk ESF's second antiderivative (``lensfit.measurement.psf``), plus
the mass of the kernel's far tail beyond the first knot. One ``H`` per knot: 97 per profile
point, where a quadrature of the pixel profile over 52 nodes of the LSF took 312 (four ``H`` and
two ``G`` per node) and was off by up to 4.4e-3 of the edge's contrast (its outer cells, 1.5-3 px
wide at ``a = 2 px``, each lumped at a point); the knots are within 2.1e-4 for ``a`` of
0.05-8 px, out to 30 px from the edge (tests/measurement/test_diffraction.py, against the product of the
pupil's, the disk's and the pixel's transfer functions).

The LSF comes from the circular pupil's transfer function,
``OTF(v) = (2/pi)(acos v - v sqrt(1 - v^2))`` for ``v = nu a <= 1`` (Goodman, *Introduction to
Fourier Optics*, sec. 6.3): ``ESF(x) = 1/2 + int_0^1 OTF(v) sin(2 pi v x) / (pi v) dv`` (in units
of ``a``).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np

from lensfit.optics.checks import namespace

#: Default wavelength (nm): the middle of the visible band, where a grey or green-weighted
#: image has its effective wavelength.
DEFAULT_WAVELENGTH_NM = 550.0
#: Largest Airy scale (px) the edge estimator's diffraction model takes: beyond it the pattern
#: spans more than the windows the profile has (f/64 at 550 nm on 1 um pixels is 35 px).
MAX_AIRY_PX = 64.0
#: The edge kernel's knots (:func:`edge_kernel`): intervals over the core (``KERNEL_CORE_AIRY``
#: Airy scales plus the pixel footprint's half-width either side of the centre), intervals a side
#: outside it, growing geometrically out to ``KERNEL_REACH_AIRY`` Airy scales (the LSF's mass
#: beyond: 0.16 %, a constant across any window, halved between the two sides).
KERNEL_CORE_INTERVALS = 48
KERNEL_OUTER_INTERVALS = 24
KERNEL_CORE_AIRY = 3.0
KERNEL_REACH_AIRY = 40.0
KERNEL_REACH_PX = 32.0
KERNEL_KNOTS = KERNEL_CORE_INTERVALS + 1 + 2 * KERNEL_OUTER_INTERVALS
#: Smallest Airy scale (px) the kernel is built for; below it the pattern is taken at this scale.
#: The pattern's 1/x^2 tails make even a small one count: a 0.1 px pattern taken for a 0.02 px one
#: moved an edge profile by 2.6e-2 of its contrast; at 0.01 px, within 4e-4.
KERNEL_MIN_AIRY_PX = 0.01
#: Gauss-Legendre points for the average over the narrower of the pixel's two boxes, and their
#: nodes and weights (computed once: numpy's eigenvalue solve for them took 0.2 ms, a tenth of
#: a kernel's time where the edge fits ask for a few edges' kernels at a time).
_BOX_POINTS = 16
_BOX_NODES, _BOX_WEIGHTS = np.polynomial.legendre.leggauss(_BOX_POINTS)

def airy_scale_px(wavelength_nm: float, working_f_number: float, pixel_pitch_mm: float) -> float:
    """``a = lambda N_w / p``: the Airy pattern's scale in pixels (first dark ring at 1.22 a)."""
    return wavelength_nm * 1e-6 * working_f_number / pixel_pitch_mm


def circular_mtf(v):
    """The diffraction-limited MTF of a circular pupil at ``v`` = frequency x lambda N (the
    transform of the Airy pattern's line spread function), NumPy or JAX as ``v`` is."""
    xp = namespace(v)
    vc = xp.clip(xp.abs(v), 0.0, 1.0)
    return (2.0 / math.pi) * (xp.arccos(vc) - vc * xp.sqrt(xp.maximum(1.0 - vc * vc, 0.0)))


def airy_esf(x: np.ndarray, nodes: int = 20000) -> np.ndarray:
    """Edge-spread function of the Airy pattern at ``x`` (units of a), by the midpoint rule."""
    x = np.asarray(x, np.float64)
    v = (np.arange(nodes) + 0.5) / nodes
    g = circular_mtf(v) / (np.pi * v) / nodes
    out = np.empty(x.size)
    flat = x.ravel()
    for i in range(0, flat.size, 512):
        out[i:i + 512] = 0.5 + np.sin(2.0 * np.pi * np.outer(flat[i:i + 512], v)) @ g
    return out.reshape(x.shape)


def airy_lsf(x: np.ndarray, nodes: int = 20000) -> np.ndarray:
    """Line-spread function of the Airy pattern at ``x`` (units of a; unit area), by the midpoint
    rule: ``2 int_0^1 OTF(v) cos(2 pi v x) dv``."""
    x = np.asarray(x, np.float64)
    v = (np.arange(nodes) + 0.5) / nodes
    g = 2.0 * circular_mtf(v) / nodes
    return (np.cos(2.0 * np.pi * np.outer(x.ravel(), v)) @ g).reshape(x.shape)


#: The table behind :func:`_airy_esf_fast`: 1/32 apart up to 8 (the pattern is band-limited to
#: one cycle per unit, so cubic Hermite interpolation is within 1e-6 there), then 2 % wider per
#: step up to beyond 420 (past every knot of :func:`edge_kernel`), where 1 - ESF falls as 1/u.
_TABLE_NODES = 8000


@lru_cache(maxsize=1)
def _esf_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u = np.concatenate([np.arange(0.0, 8.0, 1.0 / 32.0), 8.0 * 1.02 ** np.arange(0, 200)])
    return u, airy_esf(u, _TABLE_NODES), airy_lsf(u, _TABLE_NODES)


def _airy_esf_fast(u: np.ndarray) -> np.ndarray:
    """The Airy ESF at ``a = 1`` from :func:`_esf_table` by cubic Hermite interpolation (values and
    slopes), odd about (0, 1/2); beyond the table its 1/u tail."""
    grid, esf, lsf = _esf_table()
    x = np.abs(np.asarray(u, np.float64))
    k = np.clip(np.searchsorted(grid, x) - 1, 0, len(grid) - 2)
    h = grid[k + 1] - grid[k]
    t = np.clip((x - grid[k]) / h, 0.0, 1.0)
    t2, t3 = t * t, t * t * t
    inside = ((2 * t3 - 3 * t2 + 1) * esf[k] + (t3 - 2 * t2 + t) * h * lsf[k]
              + (-2 * t3 + 3 * t2) * esf[k + 1] + (t3 - t2) * h * lsf[k + 1])
    value = np.where(x <= grid[-1], inside, 1.0 - (1.0 - esf[-1]) * grid[-1] / np.maximum(x, grid[-1]))
    return np.where(np.asarray(u) >= 0, value, 1.0 - value)


def edge_kernel(airy_px, nx, ny) -> tuple[np.ndarray, np.ndarray, Any]:
    """The Airy LSF of scale ``airy_px`` convolved with a unit square pixel seen along the edge
    normal (``nx``, ``ny``), as a piecewise-linear kernel (see the module docstring); scalars, or
    arrays of one shape for many edges at once.

    Returns ``(knots_px, slope_changes, tail)``: ``KERNEL_KNOTS`` knots (px, ascending; a last
    axis after the arguments' shape), the kernel's change of slope at each, and the kernel's mass
    left of the first knot; an edge profile rising towards +x blurred by a uniform disk of radius
    R is then ``tail + sum_j c_j R^2 H((x - xi_j) / R)`` (``lensfit.measurement.psf.disk_esf_integral2``)."""
    alpha = np.maximum(np.asarray(airy_px, np.float64), KERNEL_MIN_AIRY_PX)[..., None]
    a = np.maximum(np.abs(nx), np.abs(ny))[..., None]
    b = np.minimum(np.abs(nx), np.abs(ny))[..., None]
    core = 0.5 * (a + b) + KERNEL_CORE_AIRY * alpha
    reach = 0.5 * (a + b) + np.maximum(KERNEL_REACH_AIRY * alpha, KERNEL_REACH_PX)
    outer = core * (reach / core) ** (np.arange(1, KERNEL_OUTER_INTERVALS + 1) / KERNEL_OUTER_INTERVALS)
    inner = core * np.linspace(-1.0, 1.0, KERNEL_CORE_INTERVALS + 1)
    knots = np.concatenate([-outer[..., ::-1], inner, outer], axis=-1)
    # The LSF averaged over the pixel's two boxes: the ESF's difference across the wider one,
    # averaged over the narrower one by Gauss-Legendre.
    t, w = _BOX_NODES, _BOX_WEIGHTS
    x = knots[..., None] - 0.5 * b[..., None] * t
    wide, scale = 0.5 * a[..., None], alpha[..., None]
    k = ((_airy_esf_fast((x + wide) / scale) - _airy_esf_fast((x - wide) / scale)) / (2.0 * wide)) @ (0.5 * w)
    # Linear interpolation between knots loses h^2 K'' / 12 of the mass per unit length: put it back.
    h = np.diff(knots, axis=-1)
    second = (2.0 * ((k[..., 2:] - k[..., 1:-1]) / h[..., 1:] - (k[..., 1:-1] - k[..., :-2]) / h[..., :-1])
              / (h[..., 1:] + h[..., :-1]))
    k[..., 1:-1] -= second * h[..., :-1] * h[..., 1:] / 12.0
    k[..., 0] = k[..., -1] = 0.0
    slope = np.diff(k, axis=-1) / h
    zero = np.zeros(slope.shape[:-1] + (1,))
    changes = np.diff(np.concatenate([zero, slope, zero], axis=-1), axis=-1)
    mass = np.sum(0.5 * (k[..., 1:] + k[..., :-1]) * h, axis=-1)
    return knots, changes, 0.5 * (1.0 - mass)


def working_f_number(pinhole_distance_mm: float, aperture_diameter_mm: float) -> float:
    """``N_w = S / A``: the image-side f-number of the cone that converges on the sensor (for a
    thick lens too: the exit pupil ``P A`` at ``s_x = P S`` from the sensor)."""
    if not (math.isfinite(pinhole_distance_mm) and math.isfinite(aperture_diameter_mm) and aperture_diameter_mm > 0):
        raise ValueError("working f-number needs a finite pinhole distance and a positive aperture")
    return pinhole_distance_mm / aperture_diameter_mm
