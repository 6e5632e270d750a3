"""The blur model (module notes of ``lensfit.fitting``): one function, in its inputs' namespace (JAX or NumPy)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lensfit.fitting.constants import BLUR_POWER_MEAN, EPS_PX, NODES_W
from lensfit.optics.checks import namespace


class Layout(NamedTuple):
    """Where each parameter sits in the solver's flat vector, for ``m`` settings: ``log f``;
    per setting ``k`` the inverse focus distance in dioptres (``inv_focus_per_m(k)``), ``log N``
    (``log_n(k)``) and the blur floor in px (``floor(k)``); ``log P``; then per setting the field
    curvature in dioptres (``curvature(k)``: how far the in-focus inverse distance moves per unit
    squared tangent of the field angle). Without ``k``, the slice of all settings."""

    m: int

    LOG_F = 0

    @property
    def size(self) -> int:
        return 2 + 4 * self.m

    def curvature(self, k: int | None = None):
        return slice(2 + 3 * self.m, 2 + 4 * self.m) if k is None else 2 + 3 * self.m + k

    def inv_focus_per_m(self, k: int | None = None):
        return slice(1, 1 + self.m) if k is None else 1 + k

    def log_n(self, k: int | None = None):
        return slice(1 + self.m, 1 + 2 * self.m) if k is None else 1 + self.m + k

    def floor(self, k: int | None = None):
        return slice(1 + 2 * self.m, 1 + 3 * self.m) if k is None else 1 + 2 * self.m + k

    @property
    def log_p(self) -> int:
        return 1 + 3 * self.m


class Params(NamedTuple):
    """The fit's parameters by name, read from the solver's flat vector (:func:`unpack`; where
    each sits: :class:`Layout`): ``log f``; per setting the inverse focus distance in dioptres,
    ``log N``, the blur floor in px and the field curvature in dioptres; ``log P``. A pytree of
    the vector's backend's arrays."""

    log_f: object
    inv_focus_per_m: object
    log_n: object
    floor: object
    log_p: object
    curvature: object


def unpack(theta, m) -> Params:
    """The parameters of the flat vector ``theta`` for ``m`` settings, by name."""
    at = Layout(m)
    return Params(theta[at.LOG_F], theta[at.inv_focus_per_m()], theta[at.log_n()], theta[at.floor()],
                  theta[at.log_p], theta[at.curvature()])


def vector_size(m: int) -> int:
    """Length of the parameter vector for ``m`` settings."""
    return Layout(m).size


def pinhole_distance(f, x, P):
    """``S = 1 / (1/f - x/P)``: the distance a pinhole calibration centred on the entrance pupil
    measures (``f_px * p``), for focus at inverse distance ``x`` (1/mm) from the entrance pupil
    (paraxial thick lens, module notes; ``s`` of the thin lens at ``P = 1``). Focus
    nearer than the lens can image is clamped."""
    return 1.0 / namespace(f, x, P).maximum(1.0 / f - x / P, 1e-6 / f)


def _edge_blur(slope_px, x, w_nodes, floor):
    """Blur an edge estimate reports: the power mean (``BLUR_POWER_MEAN``) over the edge of
    the local blur ``sqrt((K/p)^2 (x - 1/d)^2 + b^2)``, by Gauss-Legendre quadrature."""
    xp = namespace(slope_px, x, w_nodes, floor)
    local = xp.sqrt(slope_px[:, None] ** 2 * (x[:, None] - w_nodes) ** 2 + floor[:, None] ** 2 + EPS_PX**2)
    return (local**BLUR_POWER_MEAN @ NODES_W) ** (1.0 / BLUR_POWER_MEAN)


def _distance_scale(s, pitch, fpx_cal):
    """``p f_px / S`` per setting: the factor that takes an inverse distance measured from a
    target's pose to the true one. A pose solved with a calibrated ``f_px`` that is ``1 + e``
    times the true ``S / p`` puts every board ``1 + e`` times too far (the board's size in the
    image is ``f_px`` times its size over its distance), so the calibration's error moves all
    of a setting's pose distances together (module notes). 1 where ``f_px`` is unknown (0)."""
    return namespace(s, fpx_cal).where(fpx_cal > 0, pitch * fpx_cal / s, 1.0)


def blur_diameters_px(theta, m, setting, w_nodes, pitch, fpx_cal, pose, field2):
    """Blur diameter in px of each sample, and the pinhole distance S per setting, in the
    namespace of its inputs (jax.numpy in the solver, NumPy for predictions: one model). ``setting``
    is each sample's setting index; ``pose`` (0/1 per sample): its distances come from a target
    pose solved with the setting's calibrated ``fpx_cal`` (per setting; 0: none), and scale with
    it; ``field2`` its squared field (0 where unknown): field curvature moves its in-focus
    inverse distance to ``x + kappa field2``."""
    xp = namespace(theta, w_nodes, fpx_cal, pose, field2)
    p = unpack(theta, m)
    kappa = p.curvature / 1000.0  # 1/mm
    f = xp.exp(p.log_f)
    x = p.inv_focus_per_m / 1000.0  # 1/mm
    s = pinhole_distance(f, x, xp.exp(p.log_p))
    slope_px = f * s / xp.exp(p.log_n) / pitch  # K/p = A S / p
    mu = 1.0 + pose * (_distance_scale(s, pitch, fpx_cal)[setting] - 1.0)
    w = w_nodes * mu[:, None] - (kappa[setting] * field2)[:, None]
    return _edge_blur(slope_px[setting], x[setting], w, p.floor[setting]), s


def model_np(theta, m, k, w_nodes, pitch, fpx_cal=0.0, pose=0.0, field2=0.0):
    """:func:`blur_diameters_px` in NumPy for samples of setting ``k`` alone; ``fpx_cal`` that setting's
    calibrated focal length in px (0: none), ``pose`` 0/1 and ``field2`` per sample or one for all."""
    n = len(w_nodes)
    fpx = np.zeros(m)
    fpx[k] = fpx_cal
    return blur_diameters_px(np.asarray(theta, np.float64), m, np.full(n, k), np.asarray(w_nodes, np.float64), pitch,
                             fpx, np.broadcast_to(np.asarray(pose, float), (n,)),
                             np.broadcast_to(np.nan_to_num(np.asarray(field2, float)), (n,)))[0]
