"""The fit's stages before the uncertainty, each a function that returns what it makes:

- :func:`start`: the closed-form start of every parameter and where the pupil magnification
  comes from (fitted, a prior, or assumed);
- :func:`free_parameters`: which parameters the solve moves;
- :class:`Problem`: what every solve of one fit shares (the free parameters, the calibration's
  and the priors' rows, the loss), with :func:`irls` (the robust fit), :func:`floor_retried`
  and :func:`evaluate` (residuals, Jacobian and reduced chi-square at a solution);
- :func:`solve`: the robust fit, field curvature kept where the data show it, a floor at 0
  tried again from above.

:func:`lensfit.fitting.core._fit` runs them, then the uncertainty and the derived quantities.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from lensfit.fitting.constants import FLOOR_START_PX
from lensfit.fitting.data import FitData
from lensfit.fitting.identifiability import (P_PRIOR_SIGMA_LOG, p_identifiable, p_start, PHOTOGRAPHIC_P_NOTE,
                                         field_spread, photographic_prior, significant_curvature)
from lensfit.fitting.model import Layout, vector_size
from lensfit.fitting.solve import (floor_escape, padded_size, predict_all, robust_scale, robust_weights,
                               shared_sigma, solver_for, solver_args, solver_residual_fn)
from lensfit.fitting.start import vertex_search
from lensfit.fitting.uncertainty import svd_covariance


@dataclass(frozen=True)
class Start:
    """The closed-form start: every parameter (``theta``), the pupil magnification's start and
    where it comes from (``p_source``: "fitted", "prior" or "assumed"; ``p_prior``: its prior
    row as (mean, weight) in log P; ``p_note``: the prior's note), and warnings."""

    theta: np.ndarray
    P0: float
    p_source: str
    p_prior: tuple[float, float]
    p_note: str | None
    warnings: tuple[str, ...]


def _focal_length_sigma_px(data: FitData) -> np.ndarray:
    """Each setting's calibrated focal length's sigma, a known one (0) held at 1e-7 of it."""
    return np.where(data.focal_length_sigma_px > 0, data.focal_length_sigma_px, 1e-7 * data.focal_length_px)


def start(data: FitData, blocked: dict, has_fpx: np.ndarray, blur_floor_px: float | None, pupil: tuple) -> Start:
    """Each setting's V by a vertex search, then f from the calibration, N from the slope and the
    pupil magnification fitted, given a prior, or assumed (never silently)."""
    m, p = len(data.labels), data.pixel_pitch_mm
    fixed_floor = blur_floor_px is not None
    theta = np.zeros(vector_size(m))
    at = Layout(m)
    verts, slopes = np.zeros(m), np.ones(m)
    for k in range(m):
        sel = data.setting == k
        x, slope, b = vertex_search(data.w_mean[sel], data.coc_px[sel], data.sigma_px[sel], np.ones(sel.sum()),
                                     not fixed_floor, blur_floor_px or 0.0)
        verts[k], slopes[k] = x, max(slope, 1e-6)
        theta[at.floor(k)] = blur_floor_px if fixed_floor else max(b, FLOOR_START_PX)

    warnings = []
    fpx_sig = _focal_length_sigma_px(data)
    usable = [k for k in range(m) if has_fpx[k] and k not in blocked]
    p_prior, p_note = (0.0, 0.0), None
    if pupil[0] == "fixed":
        P0, p_source = pupil[1], "assumed"
    elif pupil[0] == "prior":
        P0, p_source, p_prior = math.exp(pupil[1]), "prior", (pupil[1], 1.0 / pupil[2])
    else:
        fit_p, why_not = p_identifiable(data, verts, usable, fpx_sig)
        if fit_p:
            P0, p_source, p_prior = p_start(data, verts, usable), "fitted", (0.0, 1.0 / P_PRIOR_SIGMA_LOG)
        elif has_fpx.any():
            P0, p_prior, why = photographic_prior(why_not)
            p_source, p_note = "prior", PHOTOGRAPHIC_P_NOTE
            warnings.append(why)
        else:
            P0, p_source = 1.0, "assumed"
    theta[at.log_p] = math.log(P0)

    f_guess = [1 / (1 / (data.focal_length_px[k] * p) + verts[k] / P0) for k in range(m)
               if has_fpx[k] and k not in blocked]
    f_guess = f_guess or [1 / (1 / (data.focal_length_px[k] * p) + verts[k] / P0) for k in range(m) if has_fpx[k]]
    f0 = float(np.median(f_guess)) if f_guess else 50.0
    theta[at.LOG_F] = math.log(f0)
    for k in range(m):
        x = min(verts[k], 0.9 * P0 / f0)
        s = 1 / (1 / f0 - x / P0)
        theta[at.inv_focus_per_m(k)] = 1000 * x
        theta[at.log_n(k)] = math.log(f0 * s / (slopes[k] * p))
    return Start(theta, P0, p_source, p_prior, p_note, tuple(warnings))


def free_parameters(m: int, p_source: str, has_fpx: np.ndarray, blocked: dict, fixed_floor: bool) -> np.ndarray:
    """Which parameters the solve moves, field curvature held (see :meth:`Problem.with_curvature`)."""
    at = Layout(m)
    free = np.ones(vector_size(m), bool)
    free[at.log_p] = p_source != "assumed"
    if not any(has_fpx[k] and k not in blocked for k in range(m)):
        # Without a calibrated setting whose V is determined, f only scales N: held at a
        # nominal value and reported as unknown.
        free[0] = False
    for k in blocked:
        free[[at.inv_focus_per_m(k), at.log_n(k), at.floor(k)]] = False
    if fixed_floor:
        free[at.floor()] = False
    free[at.curvature()] = False
    return free


@dataclass(frozen=True)
class Problem:
    """What every solve of one fit shares: the data, the free parameters (``free_plain``
    without field curvature; ``curved``: the settings whose curvature is fitted), the
    calibration's rows (``fpx``, ``fpx_w``), the floor's prior weights, the pupil
    magnification's prior row, the blur rows in use (``row_on``), the loss and its rounds."""

    data: FitData
    free_plain: np.ndarray
    curved: tuple[int, ...]
    fpx: np.ndarray
    fpx_w: np.ndarray
    floor_w: np.ndarray
    p_prior: tuple[float, float]
    row_on: np.ndarray
    loss: str
    rounds: int

    @property
    def m(self) -> int:
        return len(self.data.labels)

    @property
    def free(self) -> np.ndarray:
        out = self.free_plain.copy()
        out[[Layout(self.m).curvature(k) for k in self.curved]] = True
        return out

    @property
    def free_idx(self) -> np.ndarray:
        return np.flatnonzero(self.free)

    def with_curvature(self, curved) -> "Problem":
        """The same problem with field curvature fitted in the settings ``curved``."""
        return dataclasses.replace(self, curved=tuple(curved))

    def args(self, theta: np.ndarray, sqrt_w_over_sigma: np.ndarray):
        """The solver's arguments with the blur rows weighted by ``sqrt_w_over_sigma``."""
        return solver_args(theta, self.free_idx, self.data, sqrt_w_over_sigma, self.fpx, self.fpx_w, self.floor_w,
                            self.p_prior)


def problem(data: FitData, free_plain: np.ndarray, curved: list[int], has_fpx: np.ndarray, blocked: dict,
            fixed_floor: bool, floor_prior_sigma_px: float, p_prior: tuple[float, float], loss: str,
            max_irls: int) -> Problem:
    """The solves' shared setting (see :class:`Problem`); blocked settings' rows are off."""
    m, n = len(data.labels), len(data.coc_px)
    fpx = np.where(has_fpx, data.focal_length_px, 0.0)
    fpx_sig = np.where(has_fpx, _focal_length_sigma_px(data), 0.0)
    fpx_w = np.where(has_fpx, 1.0 / np.maximum(fpx_sig, 1e-300), 0.0)
    floor_w = np.where(fixed_floor, 0.0, 1.0 / floor_prior_sigma_px) * np.ones(m)
    for k in blocked:
        fpx_w[k] = 0.0
        floor_w[k] = 0.0
    # Blocked settings leave the blur rows out (their parameters are held).
    row_on = np.array([data.setting[i] not in blocked for i in range(n)], float)
    free_any = bool(free_plain.any() or curved)
    rounds = 0 if not free_any else 1 if loss == "linear" else max(1, max_irls)
    return Problem(data, free_plain, tuple(curved), fpx, fpx_w, floor_w, p_prior, row_on, loss, rounds)


def irls(pb: Problem, theta: np.ndarray, rows: np.ndarray, weights: np.ndarray):
    """The robust fit over the blur rows ``rows`` (0/1 per sample), started with ``weights``;
    returns (theta, weights, converged). The first solve weights the residuals by ``weights``;
    each one after it minimises the robust loss itself (:func:`_robust_rows` of
    lensfit.fitting.solve), with each residual's scale (its sigma with its image's shared error,
    times the residuals' robust scale) taken from the solve before, until the estimates and the
    weights those scales give settle. That is the fixed point of iteratively reweighted least
    squares, reached in a few solves instead of a dozen: reweighting alone converges by a factor
    of about 7 a round and ran out its 12 rounds on the standard suite's stacks."""
    data, m, free_idx = pb.data, pb.m, pb.free_idx
    n, npad = len(data.coc_px), padded_size(len(data.coc_px))
    theta, converged, q = theta.copy(), True, None
    base = rows / data.sigma_px
    for it in range(pb.rounds):
        if q is None:
            sol, ok = solver_for(m).solve(theta[free_idx], pb.args(theta, np.sqrt(weights) * base))
        else:
            sol, ok = solver_for(m).solve_robust(theta[free_idx], pb.args(theta, base),
                                              np.concatenate([q, np.ones(npad - n)]), pb.loss)
        sol = np.asarray(sol)
        if not np.all(np.isfinite(sol)):
            return theta, weights, False
        change = np.max(np.abs(sol - theta[free_idx])) if it else np.inf
        theta[free_idx] = sol
        converged = bool(ok)
        if pb.loss == "linear":
            break
        # The robust weights judge each residual against its sigma with its image's shared
        # distance error added: an image's pose error moves all its edges' blur together, most
        # where the blur is smallest relative to its slope (near the focus plane), and judged
        # against the readings' sigma alone those images, the focus distance's best, were
        # down-weighted as outliers while the image jackknife (then the images' spread), holding
        # the weights, missed the cost
        # (1 % pose errors: 95 % intervals held the focus distance in 77 % of captures).
        shared = shared_sigma(theta, m, data, rows)
        u = (data.coc_px - predict_all(theta, m, data)) / shared
        scale = robust_scale(u[rows > 0])
        new = robust_weights(u / scale, pb.loss)
        if it and change < 1e-9 and np.max(np.abs(new - weights)) < 1e-6:
            break
        weights, q = new, shared * scale / data.sigma_px
        q = np.where(np.isfinite(q) & (q > 0.0), q, 1.0)
    return theta, weights, converged


def floor_retried(pb: Problem, theta: np.ndarray, rows: np.ndarray, weights: np.ndarray, converged: bool):
    """A free floor that ends at 0 tried again from ``FLOOR_START_PX`` with the same weights:
    the model takes it squared, so 0 is a minimum of its own whatever the data, and the robust
    solves may settle there beside a fit with a floor. Where the floor fits better, they go on
    from there (:func:`irls`)."""
    free_idx = pb.free_idx
    better = floor_escape(theta[free_idx], free_idx, pb.args(theta, np.sqrt(weights) * rows / pb.data.sigma_px),
                           pb.m)
    if better is None:
        return theta, weights, converged
    alt = theta.copy()
    alt[free_idx] = better
    return irls(pb, alt, rows, weights)


def evaluate(pb: Problem, theta: np.ndarray, weights: np.ndarray):
    """Residuals and Jacobian with ``weights``, and the reduced chi-square of the blur rows."""
    data, free_idx, row_on = pb.data, pb.free_idx, pb.row_on
    npad = padded_size(len(data.coc_px))
    args = pb.args(theta, np.sqrt(weights) * row_on / data.sigma_px)
    if free_idx.size:
        res, jac = (np.asarray(a) for a in solver_for(pb.m).evaluate(theta[free_idx], args))
    else:
        res = np.asarray(solver_residual_fn(pb.m)(theta[free_idx], args))
        jac = np.zeros((len(res), 0))
    dof = max(float(np.sum(weights[row_on > 0])) - len(free_idx), 1.0)
    return res, jac, float(np.sum(res[:npad] ** 2) / dof) if row_on.any() else 1.0


@dataclass(frozen=True)
class Solution:
    """The solve's outcome: the problem as finally posed (field curvature where kept), the
    parameters, the robust weights, whether the solver met its tolerance, and the residuals,
    Jacobian and reduced chi-square there."""

    problem: Problem
    theta: np.ndarray
    weights: np.ndarray
    converged: bool
    residuals: np.ndarray
    jacobian: np.ndarray
    chi2_reduced: float


def solve(pb: Problem, theta0: np.ndarray, field_curvature: str) -> Solution:
    """The robust fit from ``theta0``; under ``field_curvature = "auto"`` the curvature is kept
    where the data show it (|kappa| / sigma >= FIELD_CURVATURE_Z), else the fit is the one "off"
    gives, from the same start; a floor at 0 is tried again from above."""
    import jax

    n = len(pb.data.coc_px)
    with jax.enable_x64(True):
        theta, weights, converged = irls(pb, theta0, pb.row_on, np.ones(n))
        res, jac, chi2_red = evaluate(pb, theta, weights)
        if pb.curved and field_curvature == "auto":
            kept = significant_curvature(theta, pb.free_idx, svd_covariance(jac, max(1.0, chi2_red))[0], pb.m,
                                         list(pb.curved))
            if kept != list(pb.curved):
                pb = pb.with_curvature(kept)
                theta, weights, converged = irls(pb, theta0, pb.row_on, np.ones(n))
                res, jac, chi2_red = evaluate(pb, theta, weights)
        retried = floor_retried(pb, theta, pb.row_on, weights, converged)
        if retried[0] is not theta:  # a floor fitted better than the one at 0
            theta, weights, converged = retried
            res, jac, chi2_red = evaluate(pb, theta, weights)
    return Solution(pb, theta, weights, converged, res, jac, chi2_red)


def curved_settings(data: FitData, blocked: dict, field_curvature: str) -> list[int]:
    """The settings whose field curvature is fitted first: where the boards span the field."""
    if field_curvature == "off":
        return []
    return [k for k in range(len(data.labels)) if k not in blocked and field_spread(data, k)]
