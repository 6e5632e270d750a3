"""Diffraction in the blur reading: the Airy pattern's line-spread function, as quadrature.

A lens stopped down far enough is diffraction-limited: the defocus disk is convolved with the
Airy pattern of the exit pupil, whose scale is ``a = lambda N_w / p`` pixels (``N_w`` the working,
image-side f-number, ``S / A`` for any lens: the pinhole distance over the entrance-pupil
diameter; first dark ring at ``1.22 a``). Its line-spread function (LSF) falls off only as
``1 / x^2``, so its variance is unbounded and no floor added in quadrature describes it: a
uniform-disk fit to an edge blurred by a disk of ``c`` px and an Airy pattern of ``a = 1.5 px``
reads 3.1 px at ``c = 0`` and ``c + 1.2 px`` at ``c = 24`` (the excess grows with the window the
blur asks for), which leaves the f-number several per cent off (README, "Diffraction").

The edge estimator therefore convolves its model profile with the Airy LSF where the caller
gives ``a``: ``ESF(x) = sum_j w_j ESF_disk+pixel(x - a xi_j)``, with nodes ``xi_j`` and weights
``w_j`` fixed for ``a = 1`` (:func:`airy_lsf_nodes`): each weight the LSF's mass in a cell
(fine near the centre, widening outwards; the outermost cells reach to infinity), each node
the cell's centroid. The LSF comes from the circular pupil's transfer function,
``OTF(v) = (2/pi)(acos v - v sqrt(1 - v^2))`` for ``v = nu a <= 1`` (Goodman, *Introduction to
Fourier Optics*, sec. 6.3): ``ESF(x) = 1/2 + int_0^1 OTF(v) sin(2 pi v x) / (pi v) dv`` (in units
of ``a``).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

#: Default wavelength (nm): the middle of the visible band, where a grey or green-weighted
#: image has its effective wavelength.
DEFAULT_WAVELENGTH_NM = 550.0
#: Cell boundaries of the quadrature for a = 1 (one side; mirrored): 1/8 up to 2, then x 1.4 up to
#: 41 (26 cells a side with the tail beyond: 52 nodes).
_INNER = np.arange(0.0, 2.0 + 1e-9, 0.125)
_OUTER = 2.0 * 1.4 ** np.arange(1, 10)


def airy_scale_px(wavelength_nm: float, working_f_number: float, pixel_pitch_mm: float) -> float:
    """``a = lambda N_w / p``: the Airy pattern's scale in pixels (first dark ring at 1.22 a)."""
    return wavelength_nm * 1e-6 * working_f_number / pixel_pitch_mm


def _otf(v: np.ndarray) -> np.ndarray:
    vc = np.clip(np.abs(v), 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(vc) - vc * np.sqrt(1.0 - vc * vc))


def airy_esf(x: np.ndarray, nodes: int = 20000) -> np.ndarray:
    """Edge-spread function of the Airy pattern at ``x`` (units of a), by the midpoint rule."""
    x = np.asarray(x, np.float64)
    v = (np.arange(nodes) + 0.5) / nodes
    g = _otf(v) / (np.pi * v) / nodes
    out = np.empty(x.size)
    flat = x.ravel()
    for i in range(0, flat.size, 512):
        out[i:i + 512] = 0.5 + np.sin(2.0 * np.pi * np.outer(flat[i:i + 512], v)) @ g
    return out.reshape(x.shape)


@lru_cache(maxsize=1)
def airy_lsf_nodes() -> tuple[np.ndarray, np.ndarray]:
    """Quadrature (nodes, weights) of the Airy LSF for a = 1: symmetric, weights summing to 1."""
    bounds = np.concatenate([_INNER, _OUTER])
    cdf = airy_esf(bounds)
    mass = np.diff(cdf)
    # Centroids by the density on a fine grid inside each cell.
    nodes = []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        x = np.linspace(lo, hi, 65)
        dens = np.gradient(airy_esf(x), x)
        nodes.append(float(np.sum(x * dens) / np.sum(dens)))
    tail = 1.0 - float(cdf[-1])  # beyond the last boundary: at 1.5 times it
    nodes.append(1.5 * float(bounds[-1]))
    mass = np.append(mass, tail)
    xi = np.concatenate([-np.array(nodes)[::-1], np.array(nodes)])
    w = np.concatenate([mass[::-1], mass])
    return xi, w / w.sum()


def working_f_number(pinhole_distance_mm: float, aperture_diameter_mm: float) -> float:
    """``N_w = S / A``: the image-side f-number of the cone that converges on the sensor (for a
    thick lens too: the exit pupil ``P A`` at ``s_x = P S`` from the sensor)."""
    if not (math.isfinite(pinhole_distance_mm) and math.isfinite(aperture_diameter_mm) and aperture_diameter_mm > 0):
        raise ValueError("working f-number needs a finite pinhole distance and a positive aperture")
    return pinhole_distance_mm / aperture_diameter_mm
