"""The solver: weighted residuals, the compiled Levenberg-Marquardt, robust reweighting."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from lensfit.fitting.constants import FLOOR_SADDLE_PX, FLOOR_START_PX, CAUCHY_C, HUBER_K
from lensfit.fitting.data import FitData
from lensfit.fitting.model import Layout, blur_diameters_px, pinhole_distance, unpack


class Rows(NamedTuple):
    """The fit's rows as the compiled solver takes them (a pytree of arrays; :func:`solver_args`
    pads the samples to :func:`padded_size`). Blur rows, one per sample: its setting's index,
    its edge's inverse distances at the Gauss-Legendre nodes (1/mm), 1 where its distance is a
    target pose's, its squared field radius, its reading and its weight (``sqrt(w) / sigma``, 0
    for padding and rows left out). Then per setting the calibration's row (the focal length in
    px and its weight, 1 / sigma) and the floor prior's weight, and log P's prior (its centre
    and weight; weight 0: none)."""

    setting: np.ndarray
    w_nodes: np.ndarray
    pose: np.ndarray
    field2: np.ndarray
    coc_px: np.ndarray
    weight: np.ndarray
    pixel_pitch_mm: float
    focal_length_px: np.ndarray
    focal_length_weight: np.ndarray
    floor_weight: np.ndarray
    p_prior: np.ndarray


class SolverArgs(NamedTuple):
    """What the compiled solver functions take beside the free parameters: the whole parameter
    vector (``lensfit.fitting.model.Layout``; its free entries, ``free_idx``, are the solver's) and
    the rows."""

    theta: np.ndarray
    free_idx: np.ndarray
    rows: Rows


def _residuals(theta_free, args: SolverArgs, m: int):
    """Weighted residuals: blur rows, then the focal-length-in-px rows, then the floor priors,
    then log P's prior."""
    import jax.numpy as jnp

    rows = args.rows
    theta = jnp.asarray(args.theta).at[args.free_idx].set(theta_free)  # numpy where called eagerly
    c, s = blur_diameters_px(theta, m, rows.setting, rows.w_nodes, rows.pixel_pitch_mm, rows.focal_length_px, rows.pose,
                             rows.field2)
    r_blur = (c - rows.coc_px) * rows.weight
    r_fpx = (s / rows.pixel_pitch_mm - rows.focal_length_px) * rows.focal_length_weight
    at = Layout(m)
    r_floor = theta[at.floor()] * rows.floor_weight
    r_p = ((theta[at.log_p] - rows.p_prior[0]) * rows.p_prior[1])[None]
    return jnp.concatenate([r_blur, r_fpx, r_floor, r_p])


#: The modules whose source defines the compiled solver (a change traces it afresh; lensfit.runtime.jaxcache).
AOT_MODULES = ("lensfit.fitting.solve", "lensfit.fitting.model", "lensfit.fitting.constants", "lensfit.fitting.lm",
               "lensfit.optics.checks")


#: Levenberg-Marquardt's tolerances. optimistix stops at an accepted step that moved every
#: parameter by less than ``SOLVE_ATOL + SOLVE_RTOL |y|`` and every residual (in sigmas) by less
#: than ``SOLVE_ATOL + SOLVE_RTOL |r|``. The residuals' own rounding is about 1e-13-1e-12 sigma (a
#: blur of tens of px, differences times weights of tens), so with an absolute part of 1e-12 a
#: residual near 0 could not pass at the minimum: the solver went on, rejecting steps on rounding
#: noise until one happened to be accepted (a solve started at its solution took up to 20 steps).
#: 1e-9 (a billionth of a sigma, of a px of floor, of log f and log N) ends there: the demo's 45
#: solves 945 -> 596 steps, 0.28 -> 0.19 s, the parameters within 1.3e-11 of before.
SOLVE_RTOL = 1e-10
SOLVE_ATOL = 1e-9


def _levenberg_marquardt(fn, theta0, args, rtol: float = SOLVE_RTOL, atol: float = SOLVE_ATOL):
    """optimistix's Levenberg-Marquardt on residuals ``fn(theta, args)``: (theta, converged)."""
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(fn, solver, theta0, args=args, max_steps=400, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful


def _optx_solve(theta0, args, m: int, rtol: float = SOLVE_RTOL, atol: float = SOLVE_ATOL):
    return _levenberg_marquardt(solver_residual_fn(m), theta0, args, rtol, atol)


def _robust_rows(r, q, loss: str):
    """Blur residuals ``r`` (in their sigmas) under the robust loss: ``sign(r) sqrt(2 rho_q(r))``
    with ``rho_q(r) = q^2 rho(r / q)`` (``q``: each row's scale, in its sigmas), so that their
    sum of squares is the robust objective and its stationary point is the reweighting's fixed
    point (weights ``psi(u) / u``, :func:`robust_weights`). Huber: ``r`` within ``k q``, beyond
    it ``sqrt(2 t |r| - t^2)``, ``t = k q``; Cauchy: ``a sqrt(log(1 + (r / a)^2))``, ``a = c q``.
    Both branches kept finite, so that the unused one's derivative is no NaN."""
    import jax.numpy as jnp

    if loss == "huber":
        t = HUBER_K * q
        inside = jnp.abs(r) <= t
        a = jnp.where(inside, t, jnp.abs(r))
        return jnp.where(inside, r, jnp.sign(r) * jnp.sqrt(2.0 * t * a - t * t))
    a = CAUCHY_C * q
    x = r / a
    small = jnp.abs(x) < 1e-4
    xs = jnp.where(small, 1.0, x)
    return jnp.where(small, r * (1.0 - 0.25 * x * x), jnp.sign(r) * a * jnp.sqrt(jnp.log1p(xs * xs)))


def _optx_solve_robust(theta0, args, q, m: int, loss: str):
    def fn(theta_free, a):
        res = _residuals(theta_free, a[0], m)
        n = a[1].shape[0]
        return res.at[:n].set(_robust_rows(res[:n], a[1], loss))

    return _levenberg_marquardt(fn, theta0, (args, q))


def _evaluate(theta, args, m: int):
    from lensfit.fitting.lm import residuals_and_jacobian

    return residuals_and_jacobian(solver_residual_fn(m), theta, args)


def _quantities(t, m: int):
    import jax.numpy as jnp

    p = unpack(t, m)
    f = jnp.exp(p.log_f)
    s = pinhole_distance(f, p.inv_focus_per_m / 1000.0, jnp.exp(p.log_p))
    return {"log_f": p.log_f, "log_N": p.log_n, "log_s": jnp.log(s), "log_A": p.log_f - p.log_n,
            "log_K": p.log_f + jnp.log(s) - p.log_n, "inv_focus_per_m": p.inv_focus_per_m, "floor": p.floor, "s": s,
            "N": jnp.exp(p.log_n), "f": f, "log_P": p.log_p, "log_sx": p.log_p + jnp.log(s)}


def _derived(t, m: int):
    import jax

    return _quantities(t, m), jax.jacfwd(_quantities)(t, m)


class _Solver:
    """The compiled functions for ``m`` settings, each traced once per installation where the CLI
    keeps a store (``lensfit.runtime.jaxcache``), else jit-compiled per process: ``solve(theta0, args) ->
    (theta, converged)`` (optimistix Levenberg-Marquardt), ``evaluate(theta, args) ->
    (residuals, Jacobian)`` and ``derived(theta_full) -> (values, Jacobians)`` of the reported
    quantities; ``args`` a :class:`SolverArgs`."""

    def __init__(self, m: int):
        self.m = m

    def _call(self, name, fn, *args, **static):
        from lensfit.runtime import jaxcache

        return jaxcache.call(f"fit-{name}", fn, args, {"m": self.m, **static}, AOT_MODULES)

    def solve(self, theta0, args):
        return self._call("solve", _optx_solve, theta0, args)

    def solve_robust(self, theta0, args, q, loss: str):
        """``solve`` under the robust ``loss`` with each blur row's scale ``q`` (in its sigmas,
        padded as the rows; :func:`_robust_rows`): the weights of ``args`` are ``rows / sigma``."""
        return self._call("solve-robust", _optx_solve_robust, theta0, args, q, loss=loss)

    def evaluate(self, theta, args):
        return self._call("evaluate", _evaluate, theta, args)

    def derived(self, t):
        return self._call("derived", _derived, t)


def solver_for(m: int) -> _Solver:
    """The compiled solver functions for ``m`` settings (see :class:`_Solver`)."""
    return _Solver(m)


def floor_escape(sol, free_idx, args, m: int):
    """The free parameters solved again with every free floor of ``sol`` that lies within
    ``FLOOR_SADDLE_PX`` of 0 started at ``FLOOR_START_PX``, where that fits better (a lower cost
    by more than a billionth); else None. The model takes each floor squared, so a floor at 0 is
    a stationary point whatever the data: a solve that reaches it, or starts there, stays there
    even where a floor fits better. The fit (``lensfit.fitting.core``) looks beyond it this way."""
    lo = Layout(m).floor(0)
    near = [k for k, j in enumerate(free_idx) if lo <= j < lo + m and abs(sol[k]) < FLOOR_SADDLE_PX]
    if not near:
        return None
    start = np.array(sol, np.float64)
    start[near] = FLOOR_START_PX
    alt = np.asarray(solver_for(m).solve(start, args)[0])
    if not np.all(np.isfinite(alt)):
        return None
    cost = [float(np.sum(np.asarray(solver_for(m).evaluate(t, args)[0]) ** 2)) for t in (sol, alt)]
    return alt if cost[1] < cost[0] * (1.0 - 1e-9) else None


def likely_free_counts(m: int) -> tuple[int, ...]:
    """The numbers of free parameters a fit of ``m`` settings most likely solves for, in the order
    it meets them: ``log f`` and per setting the focus, ``log N`` and the floor, ``log P`` where
    two or more settings may determine it; first with every setting's field curvature free
    (``field_curvature`` "auto" starts so where the samples spread over the field), then without
    (where it is not significant; also the floor's retry)."""
    base = 1 + 3 * m + (1 if m >= 2 else 0)
    return (base + m, base)


def prewarm(m: int, n: int) -> None:
    """Load (or trace and compile) the fit's compiled functions (the robust solve for the default
    loss, Huber's) for ``m`` settings and ``n`` samples (padded as the
    fit pads them) on data with nothing to fit, so that the caller can overlap their loading with
    other work: ``lensfit.measurement.pipeline`` runs it in a background thread once the stack's edges are
    known, while they are measured (a fresh process spent 0.3-0.5 s of the fit loading them;
    ``lensfit.runtime.jaxcache``). Which functions the fit then calls depends on its data
    (:func:`likely_free_counts` guesses); one it did not load here loads at its first call. SciPy's
    special functions, which the intervals take, are imported here too."""
    import jax

    from lensfit.fitting.constants import EDGE_NODES
    from lensfit.fitting.model import vector_size

    # n samples with zero weights, through the fit's own argument builder (the same dtypes and
    # padding as the fit's): the solver meets a zero residual and stops at once
    data = FitData(labels=[str(k) for k in range(m)], setting=np.zeros(n, int), distance_mm=np.ones(n),
                   w_mean=np.full(n, 1e-3), w_nodes=np.full((n, EDGE_NODES), 1e-3), coc_px=np.ones(n),
                   sigma_px=np.ones(n), pixel_pitch_mm=1.0, focal_length_px=np.zeros(m),
                   focal_length_sigma_px=np.zeros(m), pose=np.zeros(n, bool), field2=np.zeros(n))
    theta = np.zeros(vector_size(m))
    solver = solver_for(m)
    with jax.enable_x64(True):
        for k in likely_free_counts(m):
            free_idx = np.arange(min(k, theta.size), dtype=np.int64)
            full = solver_args(theta, free_idx, data, np.zeros(n), np.zeros(m), np.zeros(m), np.zeros(m))
            jax.block_until_ready(solver.solve(theta[free_idx], full))
            jax.block_until_ready(solver.solve_robust(theta[free_idx], full, np.ones(padded_size(n)), "huber"))
            jax.block_until_ready(solver.evaluate(theta[free_idx], full))
        jax.block_until_ready(solver.derived(theta))
    import scipy.special  # noqa: F401 - the intervals' Student-t quantiles (0.07 s of a fresh fit)


def robust_weights(u: np.ndarray, loss: str) -> np.ndarray:
    a = np.abs(u)
    if loss == "huber":
        return np.where(a <= HUBER_K, 1.0, HUBER_K / np.maximum(a, 1e-300))
    if loss == "cauchy":
        return 1.0 / (1.0 + (a / CAUCHY_C) ** 2)
    return np.ones_like(a)


#: The median of a standard normal's absolute value (MAD's consistency constant).
_NORMAL_MAD = 0.6745


def robust_scale(u: np.ndarray) -> float:
    """Scale of standardised residuals: 1 when the stated sigmas are honest, more when not
    (median absolute residual / 0.6745, never below 1)."""
    return max(1.0, float(np.median(np.abs(u))) / _NORMAL_MAD) if u.size else 1.0


class ImageScatter(NamedTuple):
    """The images' shared distance errors (:func:`image_scatter`): per sample, the blur's slope
    in log inverse distance ``slope`` (px) and ``shared``, the part of its residual its image's
    fitted shared error explains (``slope * delta_i``; 0 where the sample names no image); ``tau``
    the scatter of the images' shared errors (relative) beyond what their readings' sigmas
    explain, from ``images`` images; ``gain`` each image's ``c_i`` (:func:`_shift_response`)
    where ``tau`` was read through them, else None."""

    slope: np.ndarray
    shared: np.ndarray
    tau: float
    images: int
    gain: np.ndarray | None = None


def image_scatter(theta, m: int, data: FitData, rows: np.ndarray, jac=None, cov_fit=None) -> ImageScatter:
    """The images' shared distance errors: an error of an image's pose moves all of its
    distances by one factor ``exp(delta_i)``, its blur by ``delta_i g``, ``g = dc / d ln w``. Per
    image the weighted least-squares ``delta_i`` of its residuals (``rows``: the samples'
    weights), and the scatter ``tau`` of those beyond their standard errors
    (:func:`_between_scale`). The fit takes part of their spread and passes the errors of the
    images that set its parameters on to the others' fitted errors: given the fit's weighted
    Jacobian ``jac`` and its ``cov_fit`` = ``(J'J)^-1`` (the covariance's call), ``tau`` is read
    through each image's response (:func:`_shift_response`); without them (the robust weights'
    calls, between solves) as if each fitted error were its drawn one."""
    import dataclasses

    h = 1e-4
    up = predict_all(theta, m, dataclasses.replace(data, w_nodes=data.w_nodes * (1 + h)))
    down = predict_all(theta, m, dataclasses.replace(data, w_nodes=data.w_nodes * (1 - h)))
    slope = (up - down) / (2 * h)
    shared = np.zeros(len(slope))
    named = (data.group >= 0) & (rows > 0)
    if not named.any():
        return ImageScatter(slope, shared, 0.0, 0)
    resid = data.coc_px - 0.5 * (up + down)
    groups = np.unique(data.group[named])
    deltas, ses = np.zeros(len(groups)), np.full(len(groups), np.inf)
    through = None if jac is None or cov_fit is None else np.zeros((len(groups), jac.shape[1]))
    for i, g in enumerate(groups):
        sel = np.flatnonzero((data.group == g) & (rows > 0))
        info = float(np.sum(rows[sel] * (slope[sel] / data.sigma_px[sel]) ** 2))
        if info > 0:
            deltas[i] = float(np.sum(rows[sel] * slope[sel] * resid[sel] / data.sigma_px[sel] ** 2)) / info
            ses[i] = 1.0 / math.sqrt(info)
            shared[sel] = slope[sel] * deltas[i]
        if through is not None:  # B = S'J: the image's shift direction in the weighted rows, through J
            through[i] = jac[sel].T @ (np.sqrt(rows[sel]) * slope[sel] / data.sigma_px[sel])
    gain = noise = None
    if through is not None and np.all(np.isfinite(ses)):
        gain, noise = _shift_response(through, ses, cov_fit)
    return ImageScatter(slope, shared, _between_scale(deltas, ses, gain, noise), int(np.sum(np.isfinite(ses))), gain)


def _shift_response(through: np.ndarray, ses: np.ndarray, cov_fit: np.ndarray):
    """How the images' fitted shared errors respond to their true ones, once the fit has taken
    its part: with ``S`` the images' shift directions in the fit's weighted residuals (column
    ``i``: image ``i``'s samples' ``sqrt(w) g / sigma``, ``S'S = A = diag(1 / se_i^2)``),
    ``B = S'J`` (``through``, a row per image) and ``Q = A^-1 B H^-1 B'``, the fitted errors are
    ``(I - Q) delta`` plus their noise: image ``i``'s has variance ``c_i tau^2 + (1 - h_i)
    se_i^2``, ``c_i`` the sum of row ``i`` of ``(I - Q)^2`` (elementwise) and ``h_i = Q_ii``
    (``J`` the fit's weighted Jacobian, ``cov_fit`` its ``H^-1``). The fit's parameters absorb part of
    every image's error (``h_i``: the image's leverage along its shift) and pass the errors of the
    images that set them on to the others (the off-diagonal ``Q_ij``): an image far from the focus
    plane, whose own shift the blur shows weakly, read the others' through the fitted focus
    distance and scattered 2.4x the drawn errors (Monte Carlo, 10 images). Returns ``(c, 1 - h)``.

    The images' term takes the images less one for its degrees of freedom: an error and the
    scatter read beside it grow together, which keeps the ratio's tails near the normal's, and
    in Monte Carlo captures its 95 % intervals held the focus distance in 95-98 %."""
    resid = np.eye(len(ses)) - (ses**2)[:, None] * (through @ cov_fit @ through.T)
    return np.sum(resid**2, axis=1), np.clip(np.diag(resid), 0.0, 1.0)


def shared_sigma(theta, m: int, data: FitData, rows: np.ndarray) -> np.ndarray:
    """Each sample's blur sigma in px with its image's shared distance error added: ``sqrt(sigma^2
    + (g tau)^2)`` (:func:`image_scatter`); the stated sigma where ``tau`` is 0 or the samples
    name no image."""
    sc = image_scatter(theta, m, data, rows)
    return np.sqrt(data.sigma_px**2 + np.where(data.group >= 0, sc.slope * sc.tau, 0.0) ** 2)


#: Huber's "proposal 2" for the images' scatter (:func:`_between_scale`): each image's squared
#: standardised error counts at most ``_SCATTER_K^2``, and the mean of the clipped squares is
#: matched to its expectation for a standard normal, ``E min(Z^2, k^2)``.
_SCATTER_K = 1.5
_SCATTER_BETA = (math.erf(_SCATTER_K / math.sqrt(2.0)) - 2.0 * _SCATTER_K * math.exp(-0.5 * _SCATTER_K**2)
                 / math.sqrt(2.0 * math.pi) + _SCATTER_K**2 * math.erfc(_SCATTER_K / math.sqrt(2.0)))


def _between_scale(deltas: np.ndarray, ses: np.ndarray, gain=None, noise=None) -> float:
    """The scatter ``tau`` of the images' shared errors beyond their standard errors: the
    ``tau >= 0`` at which the mean of ``min(delta_i^2 / v_i, k^2)``, ``v_i = noise_i se_i^2 +
    gain_i tau^2``, is its expectation for normal errors (Huber's proposal 2, ``k`` =
    ``_SCATTER_K``; 0 where the errors are within their noise), by bisection. ``gain`` and
    ``noise`` (:func:`_shift_response`; 1 where not given): how much of the true errors and of
    their noise the fitted ones carry. A wild image counts as ``k^2`` at most.

    Over ten normal draws this reads ``tau^2`` about 7 % high on average, where matching the
    median of ``|delta_i| / sqrt(v_i)`` to the normal's (0.6745) reads 18 % high and scatters a
    third more; with ``gain``, in Monte Carlo captures of 10 images, 1.00-1.12x the drawn. A
    larger ``k`` lets an image or two whose readings stray count for much more (up to ``k^2``
    each)."""
    ok = np.isfinite(ses)
    d2, se2 = deltas[ok] ** 2, ses[ok] ** 2
    gain = np.ones_like(d2) if gain is None else np.maximum(np.asarray(gain)[ok], 1e-6)
    var0 = se2 * (1.0 if noise is None else np.maximum(np.asarray(noise)[ok], 1e-6))

    def excess(tau):
        return float(np.mean(np.minimum(d2 / (var0 + gain * tau * tau), _SCATTER_K**2))) - _SCATTER_BETA

    if d2.size == 0 or excess(0.0) <= 0.0:
        return 0.0
    lo, hi = 0.0, float(np.sqrt(np.max(d2 / gain))) / math.sqrt(_SCATTER_BETA / d2.size) + 1e-300
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) > 0.0 else (lo, mid)
    return hi


def padded_size(n: int) -> int:
    """Samples are padded to a power of two (zero weight), so that stacks of similar size share
    one compiled solver."""
    return max(64, 1 << int(math.ceil(math.log2(max(n, 1)))))


def solver_args(theta, free_idx, data: FitData, sqrt_w_over_sigma, fpx, fpx_w, floor_w,
                p_prior=(0.0, 0.0)) -> SolverArgs:
    """The solver's arguments, samples padded to :func:`padded_size`. numpy arrays, which the
    compiled functions take as they are (``jnp.asarray`` compiles a small conversion per new
    shape in every process: about 0.1 s of a cold fit)."""
    pad = padded_size(len(data.coc_px)) - len(data.coc_px)

    def padded(a, fill):
        return np.concatenate([a, np.full((pad, *np.shape(a)[1:]), fill)])

    rows = Rows(setting=padded(data.setting.astype(np.int32), 0), w_nodes=padded(data.w_nodes, 1e-3),
                pose=padded(data.pose.astype(np.float64), 0.0), field2=padded(np.nan_to_num(data.field2), 0.0),
                coc_px=padded(data.coc_px, 1.0), weight=padded(sqrt_w_over_sigma, 0.0),
                pixel_pitch_mm=data.pixel_pitch_mm, focal_length_px=np.asarray(fpx, np.float64),
                focal_length_weight=np.asarray(fpx_w, np.float64), floor_weight=np.asarray(floor_w, np.float64),
                p_prior=np.asarray(p_prior, dtype=np.float64))
    return SolverArgs(np.asarray(theta, np.float64), np.asarray(free_idx), rows)


def solver_residual_fn(m: int):
    """The weighted residuals ``fn(theta_free, args)`` of a fit of ``m`` settings."""
    def fn(theta_free, args: SolverArgs):
        return _residuals(theta_free, args, m)

    return fn


def predict_all(theta: np.ndarray, m: int, data: FitData) -> np.ndarray:
    """The model's blur of every sample (NumPy), all settings at once."""
    return blur_diameters_px(np.asarray(theta, np.float64), m, data.setting, data.w_nodes, data.pixel_pitch_mm,
                             np.nan_to_num(data.focal_length_px, nan=0.0), np.asarray(data.pose, float),
                             np.nan_to_num(np.asarray(data.field2, float)))[0]
