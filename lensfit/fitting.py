"""Fit the circle-of-confusion model to blur samples: focal length, f-number, focus distance.

Model
-----
For lens setting ``k`` (a focus distance ``D_k`` and f-number ``N_k``; all settings share the
focal length ``f`` and the pupil magnification ``P``) and a sample on an edge whose ends lie at
``d0`` and ``d1`` from the entrance pupil (the lens plane of a thin lens)::

    s_k  = 1 / (1/f - 1/(P D_k))          pinhole distance S = f_px * p, mm (thin lens: P = 1,
                                          the lens-to-sensor distance)
    K_k  = A_k * s_k = f * s_k / N_k       slope of the blur "V" in inverse distance, mm^2
    c(t) = sqrt( (K_k/p)^2 * (1/D_k - 1/d(t))^2 + b_k^2 )              px, local blur
    c    = ( integral_0^1 c(t)^q dt )^(1/q),  q = BLUR_POWER_MEAN = 1.3     px, the edge's blur

with ``d(t)`` linear from ``d0`` to ``d1`` along the edge (16-node Gauss-Legendre), ``p`` the
pixel pitch and ``b_k`` the setting's blur floor in px. For a fronto-parallel edge this is
``sqrt((A s / p)^2 (1/D - 1/d)^2 + b^2)``, the textbook ``(A s / p) |1/D - 1/d|`` with a floor.

Why this form:
- A blur estimator that fits one disk to an edge whose blur varies along it reports something
  between the mean (q = 1) and the RMS (q = 2, the second moment of the mixture) of the local
  diameters; measured on ray-traced tilted squares, q = 1.3 (see ``BLUR_POWER_MEAN``).
- Blur that is not defocus (diffraction: an Airy core of diameter about ``1.68 lambda N`` for a
  disk of equal second moment; residual aberrations; sensor MTF the estimator does not model)
  convolves with the defocus disk, and variances of convolved PSFs add, so the floor adds in
  quadrature. This also makes the model smooth at the focus plane, where ``|.|`` has a kink
  (grad(abs) at 0 is arbitrary, grad(sqrt) at 0 is infinite).
- The floor is fitted per setting with a weak prior ``b_k ~ 0 +- 1 px`` (a regulariser that
  matters only when no sample lies near the focus plane), or fixed by the caller.

Thick lenses (README, "Compound (real) lenses"; data_specs/CONVENTIONS.md): with ``A`` the
entrance-pupil diameter, ``P`` the exit/entrance pupil ratio and ``s_x`` the exit pupil's
distance from the sensor, the blur is
``(A s_x / P) |1/D - 1/d|`` and a pinhole calibration centred on the entrance pupil measures
``S = s_x / P``: the V is ``A S |1/D - 1/d|`` whatever ``P`` is, and only the mapping from ``S``
to ``f`` carries ``P``: ``1/f = 1/S + 1/(P D)``. Two or more focus settings that share ``f`` and
``P`` (unit focusing) determine ``P`` (``1/S_k`` is linear in ``1/D_k``); with one setting ``P``
is an assumption (1 by default, with a warning) or a stated prior range.

Observations: the blur samples (weights from each sample's stated 1 sigma) and, per setting,
the calibrated focal length in px, ``f_px = s_k / p`` with its 1 sigma. Parameters (float64,
chosen to stay well conditioned from macro to infinity): ``log f``; per setting the inverse
focus distance ``1000/D_k`` (dioptres, 0 at infinity, allowed to cross it), ``log N_k`` and
``b_k``; ``log P`` (held where assumed; a log-normal prior where a range is given, a very weak
one where it is fitted).

Solver: a closed-form start (for each candidate vertex on a grid spanning the data, linear
least squares for the slope and floor in ``c^2``; the best vertex wins), then optimistix
Levenberg-Marquardt, inside iteratively reweighted least squares for a robust loss (Huber by
default, Cauchy for heavy contamination). The covariance is ``(J^T W J)^-1`` at the solution,
scaled by the reduced chi-square when that exceeds 1, and propagated to every derived quantity
by the delta method (log space for positive quantities, so intervals stay positive).

Identifiability: blur at one setting fixes only ``K`` and ``D``; the calibrated
``f_px`` supplies ``s``, hence ``f`` and ``N``. A parameter the data cannot determine (one
distance, blur all below a pixel, no focal length in px, a vertex extrapolated far from the
samples, a relative uncertainty over 20 %) is reported with value ``None`` and the reason and
the capture that would fix it; never a number, NaN or inf.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from lensfit.errors import InputError

#: Weak prior on each setting's blur floor (px, 1 sigma about 0).
FLOOR_PRIOR_SIGMA_PX = 1.0
#: A parameter whose relative 1 sigma exceeds this is reported as not identifiable.
MAX_RELATIVE_SIGMA = 0.2
#: Samples whose distances spread less than this (relative) count as one distance.
MIN_DISTANCE_SPREAD = 0.02
#: Below this every measured blur is pixel integration, diffraction and aberration.
MIN_USEFUL_BLUR_PX = 1.0
#: Images needed for the leave-one-image-out jackknife of the covariance (see fit).
MIN_CLUSTERS = 6
MAX_CLUSTERS = 400  # one LM solve each
#: Condition number (column-equilibrated Jacobian) above which the fit is degenerate.
MAX_CONDITION = 1e8
LOSSES = ("linear", "huber", "cauchy")
#: An edge whose ends lie at different depths has a blur that varies along it; a one-disk
#: edge fit then reports a power mean of the local blur diameters between the mean (1) and the
#: RMS (2). Measured with the edge estimator on ray-traced squares tilted 50-60 degrees (blur
#: 0-8 px along one edge, crossing focus or not): 1.3 fits within 4.2 % (mean |error| 1.6 %);
#: the mean is 1-10 % low, the RMS 5-10 % high (tests/test_fit_pipeline.py). Fronto-parallel
#: edges are unaffected.
BLUR_POWER_MEAN = 1.3
EDGE_NODES = 16
_GL_X, _GL_W = np.polynomial.legendre.leggauss(EDGE_NODES)
_NODES_T = (_GL_X + 1.0) / 2.0  # positions along the edge, 0..1
_NODES_W = _GL_W / 2.0  # weights summing to 1
_HUBER_K = 1.345
_CAUCHY_C = 2.385
_EPS_PX = 1e-4  # keeps sqrt differentiable exactly at the focus plane with a zero floor
_Z95 = 1.959963984540054

#: The ranges of physically meaningful inputs; anything outside is refused naming the field.
PIXEL_PITCH_RANGE_MM = (1e-4, 1.0)
DISTANCE_RANGE_MM = (0.1, 1e9)
MAX_BLUR_PX = 1e6
MIN_SIGMA_PX = 1e-6
MAX_FOCAL_LENGTH_PX = 1e7

QUANTITIES = ("focal_length_mm", "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm",
              "sensor_distance_mm", "aperture_diameter_mm", "blur_slope_mm2", "blur_floor_px",
              "inverse_focus_distance_per_m")


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Estimate:
    """A fitted or derived quantity. ``value`` is None when the data cannot determine it
    (``reason`` says why and what would fix it). ``infinite`` marks a focus distance at
    infinity (value None, the inverse distance is then the estimate to read). An interval end
    that is None is unbounded (a focus interval reaching infinity)."""

    value: float | None
    sigma: float | None = None
    ci68: tuple[float | None, float | None] | None = None
    ci95: tuple[float | None, float | None] | None = None
    reason: str | None = None
    infinite: bool = False

    @property
    def determined(self) -> bool:
        return self.value is not None or self.infinite

    def _decimals(self) -> int:
        """Decimals that show two significant digits of the uncertainty."""
        if not self.sigma or not math.isfinite(self.sigma):
            return 4
        return int(min(8, max(0, 1 - math.floor(math.log10(self.sigma)))))

    def text(self, unit: str = "") -> str:
        """``value ± sigma`` rounded to the uncertainty; "infinity" or "not identifiable"."""
        if self.infinite:
            return "infinity"
        if self.value is None:
            return "not identifiable"
        n = self._decimals()
        return f"{self.value:.{n}f}{unit} ± {self.sigma:.{n}f}"

    def interval_text(self) -> str:
        """The 95 % interval, an unbounded end shown as "infinity"."""
        if self.ci95 is None:
            return ""
        n = self._decimals()
        lo, hi = (("infinity" if v is None else f"{v:.{n}f}") for v in self.ci95)
        return f"[{lo}, {hi}]"

    def to_json_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"value": self.value, "sigma": self.sigma,
                               "ci68": list(self.ci68) if self.ci68 else None,
                               "ci95": list(self.ci95) if self.ci95 else None}
        if self.infinite:
            out["infinite"] = True
        if self.reason:
            out["reason"] = self.reason
        return out


@dataclass
class FitResult:
    """What ``fit`` found.

    Attributes
    ----------
    settings : label -> quantity name (see ``QUANTITIES``) -> :class:`Estimate`
    focal_length_mm : the shared focal length
    code : ``"ok"`` or ``"not_identifiable"`` (some quantity is None; see ``reasons``)
    reasons : one line per quantity that could not be determined
    parameter_names, parameters, covariance : the free parameters of the solver, their values
        and covariance (``log_f``, ``inv_focus_per_m[k]``, ``log_N[k]``, ``floor_px[k]``)
    correlations : correlation matrix of the free parameters
    condition_number : of the column-equilibrated, weighted Jacobian
    residuals_px, weights : per used sample (measured minus model; final robust weight)
    """

    settings: dict[str, dict[str, Estimate]]
    focal_length_mm: Estimate
    code: str
    reasons: list[str]
    parameter_names: list[str]
    parameters: np.ndarray
    covariance: np.ndarray
    correlations: np.ndarray
    condition_number: float
    n_samples: int
    n_outliers: int
    chi2_reduced: float
    rms_residual_px: float
    loss: str
    warnings: list[str]
    samples: "FitData"
    residuals_px: np.ndarray
    weights: np.ndarray
    _full: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    _setup: dict[str, Any] = field(repr=False, default_factory=dict)  # solver rows, for cramer_rao
    #: the pupil magnification P (exit / entrance pupil diameter) the fit used, and how:
    #: "fitted" (two or more focus settings), "prior" (a stated range) or "assumed" (a value)
    pupil_magnification: Estimate = field(default_factory=lambda: Estimate(1.0, 0.0, (1.0, 1.0), (1.0, 1.0)))
    pupil_magnification_source: str = "assumed"

    @property
    def ok(self) -> bool:
        return self.code == "ok"

    def predict_px(self, setting: str, distance_mm: np.ndarray) -> np.ndarray:
        """Model blur diameter (px) of a fronto-parallel edge at ``distance_mm`` from the lens."""
        k = self.samples.labels.index(setting)
        w = 1.0 / np.asarray(distance_mm, np.float64).reshape(-1)
        nodes = np.repeat(w[:, None], EDGE_NODES, axis=1)
        return _model_np(self._full, len(self.samples.labels), k, nodes, self.samples.pixel_pitch_mm)

    def to_json_dict(self) -> dict[str, Any]:
        """The results file (data_specs/schemas/results.schema.json); finite numbers or null throughout."""
        names = self.parameter_names
        corr = {names[i]: {names[j]: _finite(self.correlations[i, j]) for j in range(len(names))}
                for i in range(len(names))}
        return {
            "focal_length_mm": self.focal_length_mm.to_json_dict(),
            "pupil_magnification": self.pupil_magnification.to_json_dict() | {
                "source": self.pupil_magnification_source},
            "settings": {label: {q: e.to_json_dict() for q, e in qs.items()} | {"samples": int(np.sum(
                self.samples.setting == self.samples.labels.index(label)))} for label, qs in self.settings.items()},
            "result": self.code,
            "reasons": self.reasons,
            "diagnostics": {
                "condition_number": _finite(self.condition_number),
                "correlations": corr,
                "samples": self.n_samples,
                "outliers": self.n_outliers,
                "chi2_reduced": _finite(self.chi2_reduced),
                "rms_residual_px": _finite(self.rms_residual_px),
                "loss": self.loss,
                "warnings": self.warnings,
            },
        }


def _finite(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


# --------------------------------------------------------------------------- input


@dataclass
class FitData:
    """Samples in the solver's terms (float64 arrays, one entry per used sample)."""

    labels: list[str]
    setting: np.ndarray  # index into labels
    distance_mm: np.ndarray  # middle of the edge
    w_mean: np.ndarray  # <1/d> along the edge, 1/mm
    w_nodes: np.ndarray  # (n, EDGE_NODES) 1/d at the Gauss-Legendre nodes along the edge, 1/mm
    coc_px: np.ndarray
    sigma_px: np.ndarray
    pixel_pitch_mm: float
    focal_length_px: np.ndarray  # per setting, NaN = unknown
    focal_length_sigma_px: np.ndarray
    dropped: int = 0
    #: image index of each sample (errors shared by an image's edges: its pose, its noise);
    #: -1 where the samples do not name their image
    group: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    #: index of each used sample in the input rows (unmeasured rows are dropped)
    row: np.ndarray = field(default_factory=lambda: np.zeros(0, int))


def inverse_distance_moments(d0: np.ndarray, d1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of ``1/d`` for ``d`` uniform along a segment from ``d0`` to ``d1``.

    ``<1/d> = ln(d1/d0)/(d1 - d0)``, ``<1/d^2> = 1/(d0 d1)``; written with ``m`` the middle and
    ``r = (d1 - d0)/(d1 + d0)`` as ``atanh(r)/(r m)`` and ``(1/(1 - r^2) - (atanh(r)/r)^2)/m^2``,
    with the series ``r^2/3 + 22 r^4/45`` for the variance where ``|r|`` is small.
    """
    d0, d1 = np.asarray(d0, np.float64), np.asarray(d1, np.float64)
    m = (d0 + d1) / 2
    r = (d1 - d0) / (d1 + d0)
    small = np.abs(r) < 1e-3
    rs = np.where(small, 0.5, r)
    ratio = np.where(small, 1 + r**2 / 3 + r**4 / 5, np.arctanh(rs) / rs)
    var = np.where(small, r**2 / 3 + 22 * r**4 / 45, 1 / (1 - rs**2) - (np.arctanh(rs) / rs) ** 2)
    return ratio / m, np.maximum(var, 0.0) / m**2


def _rows_from(samples: Any) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Sample rows and context (pixel pitch, intrinsics) from any accepted input."""
    from lensfit.measure import SampleTable

    if isinstance(samples, (str, Path)):
        samples = SampleTable.read(samples)
    if isinstance(samples, SampleTable):
        ctx = {"pixel_pitch_mm": samples.pixel_pitch_mm,
               "focal_length_px": {k: v.focal_length_px for k, v in samples.intrinsics.items()},
               "focal_length_sigma_px": {k: v.focal_length_sigma_px for k, v in samples.intrinsics.items()}}
        return samples.rows(), ctx
    rows = []
    for s in samples:
        rows.append(dict(s) if isinstance(s, dict) else dict(vars(s)))
    return rows, {}


def _per_setting(value: Any, labels: list[str], name: str, default: float) -> np.ndarray:
    if value is None:
        return np.full(len(labels), default)
    if isinstance(value, dict):
        unknown = [k for k in value if k not in labels]
        if unknown:
            raise InputError(name, unknown[0], "a setting label of the samples: " + ", ".join(labels))
        return np.array([float(value[k]) if value.get(k) is not None else default for k in labels])
    return np.full(len(labels), float(value))


def prepare(samples: Any, *, pixel_pitch_mm: float | None = None,
            focal_length_px: float | dict[str, float] | None = None,
            focal_length_sigma_px: float | dict[str, float] | None = None) -> FitData:
    """Validate samples and turn them into :class:`FitData` (see :func:`fit`)."""
    rows, ctx = _rows_from(samples)
    pitch = pixel_pitch_mm if pixel_pitch_mm is not None else ctx.get("pixel_pitch_mm")
    if pitch is None or not (isinstance(pitch, (int, float)) and math.isfinite(pitch) and pitch > 0):
        raise InputError("pixel_pitch_mm", pitch, "> 0 mm", "give the sensor's pixel pitch (stack.toml [camera])")
    if not PIXEL_PITCH_RANGE_MM[0] <= pitch <= PIXEL_PITCH_RANGE_MM[1]:
        raise InputError("pixel_pitch_mm", pitch, f"between {PIXEL_PITCH_RANGE_MM[0]:g} and {PIXEL_PITCH_RANGE_MM[1]:g} "
                         "mm (0.1 micrometre to 1 mm)", "pixel pitches are given in mm, e.g. 0.0059 for 5.9 um")
    used, used_rows, dropped = [], [], 0
    for i, r in enumerate(rows):
        c, sg = r.get("coc_diameter_px"), r.get("sigma_px")
        d = r.get("distance_mm")
        for name in ("distance_mm", "setting"):
            if r.get(name) is None:
                raise InputError(f"samples[{i}].{name}", None, "present")
        if not (isinstance(d, (int, float)) and math.isfinite(d) and d > 0):
            raise InputError(f"samples[{i}].distance_mm", d, "> 0 mm and finite")
        if not DISTANCE_RANGE_MM[0] <= d <= DISTANCE_RANGE_MM[1]:
            raise InputError(f"samples[{i}].distance_mm", d, f"between {DISTANCE_RANGE_MM[0]:g} and "
                             f"{DISTANCE_RANGE_MM[1]:g} mm", "distances are in mm from the lens")
        if c is None or sg is None or not (math.isfinite(c) and math.isfinite(sg) and sg > 0 and c >= 0):
            dropped += 1  # the estimator could not measure this edge
            continue
        if c > MAX_BLUR_PX:
            raise InputError(f"samples[{i}].coc_diameter_px", c, f"at most {MAX_BLUR_PX:g} px",
                             "no image is that large; blur diameters are in px")
        if not MIN_SIGMA_PX <= sg <= MAX_BLUR_PX:
            raise InputError(f"samples[{i}].sigma_px", sg, f"between {MIN_SIGMA_PX:g} and {MAX_BLUR_PX:g} px",
                             "a blur measurement is never that exact (or that vague)")
        used.append(r)
        used_rows.append(i)
    if not used:
        raise InputError("samples", f"{len(rows)} rows", "at least one sample with a measured coc_diameter_px and "
                         "sigma_px", "measure a stack whose targets were detected (lensfit measure)")
    labels = sorted({str(r["setting"]) for r in used})
    idx = {k: i for i, k in enumerate(labels)}
    dist = np.array([float(r["distance_mm"]) for r in used])
    d0 = np.array([float(r.get("distance_start_mm") or r["distance_mm"]) for r in used])
    d1 = np.array([float(r.get("distance_end_mm") or r["distance_mm"]) for r in used])
    if np.any(d0 <= 0) or np.any(d1 <= 0):
        raise InputError("samples.distance_start_mm", float(min(d0.min(), d1.min())), "> 0 mm")
    w_mean, _ = inverse_distance_moments(d0, d1)
    w_nodes = 1.0 / (d0[:, None] + _NODES_T[None, :] * (d1 - d0)[:, None])
    fpx = _per_setting(focal_length_px if focal_length_px is not None else ctx.get("focal_length_px"),
                       labels, "focal_length_px", math.nan)
    fsg = _per_setting(focal_length_sigma_px if focal_length_sigma_px is not None
                       else ctx.get("focal_length_sigma_px"), labels, "focal_length_sigma_px", 0.0)
    bad = ~(np.isnan(fpx) | ((fpx >= 1.0) & (fpx <= MAX_FOCAL_LENGTH_PX)))
    if bad.any():
        raise InputError("focal_length_px", float(fpx[bad][0]), f"between 1 and {MAX_FOCAL_LENGTH_PX:g} px")
    bad = ~np.isfinite(fsg) | (fsg < 0) | (fsg > MAX_FOCAL_LENGTH_PX)
    if bad.any():
        raise InputError("focal_length_sigma_px", float(fsg[bad][0]), f"between 0 and {MAX_FOCAL_LENGTH_PX:g} px")
    images = [str(r.get("image") or "") for r in used]  # "" = not known: no jackknife over images
    image_index = {name: (i if name else -1) for i, name in enumerate(dict.fromkeys(images))}
    return FitData(labels, np.array([idx[str(r["setting"])] for r in used]), dist, w_mean, w_nodes,
                   np.array([float(r["coc_diameter_px"]) for r in used]),
                   np.array([float(r["sigma_px"]) for r in used]), float(pitch), fpx, fsg, dropped,
                   np.array([image_index[name] for name in images], int), np.array(used_rows, int))


# --------------------------------------------------------------------------- model


def _unpack(theta, m):
    """(log f, inverse focus distances in dioptres, log N, floors in px, log P) from the vector."""
    return theta[0], theta[1:1 + m], theta[1 + m:1 + 2 * m], theta[1 + 2 * m:1 + 3 * m], theta[1 + 3 * m]


def _size(m: int) -> int:
    """Length of the parameter vector for ``m`` settings."""
    return 2 + 3 * m


def _pinhole_distance(xp, f, x, P):
    """``S = 1 / (1/f - x/P)``: the distance a pinhole calibration centred on the entrance pupil
    measures (``f_px * p``), for focus at inverse distance ``x`` (1/mm) from the entrance pupil
    (paraxial thick lens, module notes; ``s`` of the thin lens at ``P = 1``). Focus
    nearer than the lens can image is clamped."""
    return 1.0 / xp.maximum(1.0 / f - x / P, 1e-6 / f)


def _edge_blur(xp, slope_px, x, w_nodes, floor):
    """Blur an edge estimate reports: the power mean (``BLUR_POWER_MEAN``) over the edge of
    the local blur ``sqrt((K/p)^2 (x - 1/d)^2 + b^2)``, by Gauss-Legendre quadrature."""
    local = xp.sqrt(slope_px[:, None] ** 2 * (x[:, None] - w_nodes) ** 2 + floor[:, None] ** 2 + _EPS_PX**2)
    return (local**BLUR_POWER_MEAN @ _NODES_W) ** (1.0 / BLUR_POWER_MEAN)


def _model(theta, m, setting, w_nodes, pitch):
    """Blur diameter in px of each sample (JAX)."""
    import jax.numpy as jnp

    log_f, inv_d, log_n, floor, log_p = _unpack(theta, m)
    f = jnp.exp(log_f)
    x = inv_d / 1000.0  # 1/mm
    s = _pinhole_distance(jnp, f, x, jnp.exp(log_p))
    slope_px = f * s / jnp.exp(log_n) / pitch  # K/p = A S / p
    k = setting
    return _edge_blur(jnp, slope_px[k], x[k], w_nodes, floor[k]), s


def _model_np(theta, m, k, w_nodes, pitch):
    """The same for the samples of setting ``k`` (NumPy)."""
    log_f, inv_d, log_n, floor, log_p = (np.asarray(a) for a in _unpack(np.asarray(theta), m))
    f = math.exp(log_f)
    x = inv_d[k] / 1000.0
    s = float(_pinhole_distance(np, f, x, math.exp(log_p)))
    n = len(w_nodes)
    return _edge_blur(np, np.full(n, f * s / math.exp(log_n[k]) / pitch), np.full(n, x), w_nodes,
                      np.full(n, floor[k]))


def _residuals(theta_free, args):
    """Weighted residuals: blur rows, then the focal-length-in-px rows, then the floor priors."""
    import jax.numpy as jnp

    (theta_fixed, free_idx, m, setting, w_nodes, coc, sqrt_w_over_sigma, pitch, fpx, fpx_w, floor_w, p_prior) = args
    theta = theta_fixed.at[free_idx].set(theta_free)
    c, s = _model(theta, m, setting, w_nodes, pitch)
    r_blur = (c - coc) * sqrt_w_over_sigma
    r_fpx = (s / pitch - fpx) * fpx_w
    r_floor = theta[1 + 2 * m:1 + 3 * m] * floor_w
    r_p = ((theta[1 + 3 * m] - p_prior[0]) * p_prior[1])[None]  # prior on log P (weight 0: none)
    return jnp.concatenate([r_blur, r_fpx, r_floor, r_p])


_SOLVERS: dict[Any, Any] = {}


def _solver(m: int):
    """Jit-compiled functions for ``m`` settings (cached per m; compiled once per shape and kept
    in the persistent cache by the CLI): ``solve(theta0, args) -> (theta, converged)`` (LM),
    ``evaluate(theta, args) -> (residuals, Jacobian)`` and ``derived(theta_full) -> (values,
    Jacobians)`` of the reported quantities."""
    if m in _SOLVERS:
        return _SOLVERS[m]
    import jax
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)
    fn = _solver_residual_fn(m)

    @jax.jit
    def solve(theta0, args):
        sol = optx.least_squares(fn, solver, theta0, args=args, max_steps=400, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful

    @jax.jit
    def evaluate(theta, args):
        return fn(theta, args), jax.jacfwd(fn)(theta, args)

    def quantities(t):
        import jax.numpy as jnp

        log_f, inv_d, log_n, floor, log_p = _unpack(t, m)
        f = jnp.exp(log_f)
        s = _pinhole_distance(jnp, f, inv_d / 1000.0, jnp.exp(log_p))
        return {"log_f": log_f, "log_N": log_n, "log_s": jnp.log(s), "log_A": log_f - log_n,
                "log_K": log_f + jnp.log(s) - log_n, "inv_d": inv_d, "floor": floor, "s": s, "N": jnp.exp(log_n),
                "f": f, "log_P": log_p, "log_sx": log_p + jnp.log(s)}

    @jax.jit
    def derived(t):
        return quantities(t), jax.jacfwd(quantities)(t)

    _SOLVERS[m] = (solve, evaluate, derived)
    return _SOLVERS[m]


# --------------------------------------------------------------------------- start


def _vertex_search(w: np.ndarray, c: np.ndarray, sig: np.ndarray, wt: np.ndarray, fit_floor: bool,
                   floor_px: float) -> tuple[float, float, float]:
    """Closed-form start for one setting: (vertex 1/mm, slope px*mm, floor px)."""
    grid, chi2, k, b = _vertex_profile(w, c, sig, wt, fit_floor, floor_px)
    best = int(np.argmin(chi2))
    return float(grid[best]), float(k[best]), float(b[best])


def _vertex_profile(w: np.ndarray, c: np.ndarray, sig: np.ndarray, wt: np.ndarray, fit_floor: bool,
                    floor_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chi-square of the best V for each candidate vertex: (vertices 1/mm, chi2, slope, floor).

    For each candidate vertex x the model ``c^2 = k^2 (x - w)^2 + b^2`` is linear in
    ``(k^2, b^2)``: weighted linear least squares (weights ``1/(2 c sigma)^2``, the variance of
    ``c^2``), then the vertex with the least chi-square in ``c``. Candidates span the samples'
    inverse distances and as much again on each side, plus infinity (x = 0).
    """
    lo, hi = float(w.min()), float(w.max())
    span = max(hi - lo, 0.05 * hi)
    # The samples' own inverse distances join the grid (as quantiles: memory stays
    # O(1000 x n) for stacks of thousands of edges).
    grid = np.unique(np.concatenate([np.linspace(max(lo - span, -0.2 * hi), hi + span, 801), [0.0],
                                     np.quantile(w, np.linspace(0.0, 1.0, min(len(w), 200)))]))
    cc = np.maximum(c, 0.05)
    a2 = (grid[:, None] - w[None, :]) ** 2  # (G, n)
    wv = wt / (2 * cc * sig) ** 2
    y = c**2 - (0.0 if fit_floor else floor_px**2)
    if fit_floor:
        # Normal equations of [a2, 1] per candidate.
        s11 = a2**2 @ wv
        s12 = a2 @ wv
        s22 = wv.sum()
        t1 = a2 @ (wv * y)
        t2 = (wv * y).sum()
        det = s11 * s22 - s12**2
        k2 = np.where(det > 0, (t1 * s22 - s12 * t2) / np.where(det > 0, det, 1), 0.0)
        b2 = np.where(det > 0, (s11 * t2 - s12 * t1) / np.where(det > 0, det, 1), 0.0)
        neg = b2 < 0  # floor cannot be negative: refit the slope alone
        k2 = np.where(neg, t1 / np.maximum(s11, 1e-300), k2)
        b2 = np.where(neg, 0.0, b2)
    else:
        k2 = (a2 @ (wv * y)) / np.maximum(a2**2 @ wv, 1e-300)
        b2 = np.full_like(k2, floor_px**2)
    k2 = np.maximum(k2, 0.0)
    pred = np.sqrt(k2[:, None] * a2 + b2[:, None])
    chi2 = ((pred - c[None, :]) ** 2 * (wt / sig**2)[None, :]).sum(axis=1)
    return grid, chi2, np.sqrt(k2), np.sqrt(b2)


def _side_hint(w: np.ndarray, x: float) -> str:
    """"; every sample is nearer/farther than the focus" when all inverse distances ``w`` lie on
    one side of the vertex ``x`` (same units), else ""."""
    if np.all(w > x):
        return "; every sample is nearer than the focus"
    if np.all(w < x):
        return "; every sample is farther than the focus"
    return ""


def _capture_problems(data: FitData) -> dict[int, str]:
    """Settings whose capture cannot determine their V, with the reason and the fix."""
    blocked: dict[int, str] = {}
    for k, label in enumerate(data.labels):
        sel = data.setting == k
        d = np.sort(data.distance_mm[sel])
        groups = np.split(d, np.flatnonzero(np.diff(d) / d[:-1] > MIN_DISTANCE_SPREAD) + 1)
        narrow = all((g.max() - g.min()) / g.mean() < MIN_DISTANCE_SPREAD for g in groups)
        if sel.sum() < 4:
            blocked[k] = (f"setting {label!r} has only {int(sel.sum())} measured edge(s); a V needs more: photograph "
                          "the target at 3 or more distances")
        elif (d.max() - d.min()) / np.median(d) < MIN_DISTANCE_SPREAD:
            blocked[k] = (f"every sample of setting {label!r} lies at one distance (~{np.median(d):.0f} mm); blur at "
                          "one distance cannot separate the V's slope from its vertex: photograph the target at 3 or "
                          "more distances, some nearer and some farther than the focus")
        elif len(groups) == 2 and narrow:
            blocked[k] = (f"the samples of setting {label!r} lie at two distances only (~{groups[0].mean():.0f} and "
                          f"~{groups[1].mean():.0f} mm); a V through two distances fits twice (focus between them, or "
                          "beyond both): photograph the target at 3 or more distances")
        elif data.coc_px[sel].max() < MIN_USEFUL_BLUR_PX:
            blocked[k] = (f"every blur of setting {label!r} is below {MIN_USEFUL_BLUR_PX:g} px (largest "
                          f"{data.coc_px[sel].max():.2f} px), where pixel integration, diffraction and aberrations "
                          "dominate: open the aperture or place targets farther from the focus plane")
    return blocked


def _robust_weights(u: np.ndarray, loss: str) -> np.ndarray:
    a = np.abs(u)
    if loss == "huber":
        return np.where(a <= _HUBER_K, 1.0, _HUBER_K / np.maximum(a, 1e-300))
    if loss == "cauchy":
        return 1.0 / (1.0 + (a / _CAUCHY_C) ** 2)
    return np.ones_like(a)


def _robust_scale(u: np.ndarray) -> float:
    """Scale of standardised residuals: 1 when the stated sigmas are honest, more when not
    (median absolute residual / 0.6745, never below 1)."""
    return max(1.0, float(np.median(np.abs(u))) / 0.6745) if u.size else 1.0


# --------------------------------------------------------------------------- fit


def fit(samples: Any, *, pixel_pitch_mm: float | None = None,
        focal_length_px: float | dict[str, float] | None = None,
        focal_length_sigma_px: float | dict[str, float] | None = None,
        loss: str = "huber", blur_floor_px: float | None = None,
        floor_prior_sigma_px: float = FLOOR_PRIOR_SIGMA_PX, max_irls: int = 12,
        pupil_magnification: float | tuple[float, float] | None = None) -> FitResult:
    """Fit focal length, and per setting f-number and focus distance, to blur samples.

    Distances are measured from the entrance pupil (the centre a pinhole calibration finds;
    the lens plane of a thin lens). The lens may be thick: its pupil magnification
    ``P`` (exit / entrance pupil diameter) enters through ``1/S = 1/f - 1/(P X)``, where
    ``S = f_px * p`` is what the calibration measures (module notes).

    Parameters
    ----------
    samples : a :class:`~lensfit.measure.SampleTable`, the path of a samples JSON/CSV written
        by ``lensfit measure``, or a sequence of rows (dicts or ``Sample``) with ``setting``,
        ``distance_mm``, ``coc_diameter_px``, ``sigma_px`` and optionally
        ``distance_start_mm``/``distance_end_mm`` (the edge's ends, for tilted edges)
    pixel_pitch_mm : sensor pixel pitch (default: the SampleTable's)
    focal_length_px : calibrated focal length in px (= sensor distance / pitch), one number or
        per setting label (default: the SampleTable's intrinsics). Without it f and N cannot
        be separated and are reported as not identifiable.
    focal_length_sigma_px : its 1 sigma (default: the calibration's; 0 = exact)
    loss : "huber" (default), "cauchy" (many outliers) or "linear"
    blur_floor_px : fix the blur floor (px) instead of fitting it per setting
    floor_prior_sigma_px : width of the weak prior on a fitted floor (about 0)
    max_irls : reweighting rounds for the robust loss
    pupil_magnification : how P is treated. None (default): fitted where two or more calibrated
        settings focus at different distances (unit focusing: they share f and P), otherwise
        assumed 1 (the thin lens) with a warning that says so and what it costs. A number:
        assumed at that value. A range ``(lo, hi)``: a prior on P (log-normal, the range its
        95 % interval), which the data may sharpen and which widens the intervals of f and N
        honestly where they cannot.

    Returns
    -------
    FitResult (``code`` "ok" or "not_identifiable"; never NaN or inf in it)

    Raises
    ------
    InputError
        No usable sample, a bad pixel pitch, focal length, loss or floor.
    """
    import jax
    import jax.numpy as jnp

    if loss not in LOSSES:
        raise InputError("loss", loss, "one of: " + ", ".join(LOSSES))
    if blur_floor_px is not None and not (math.isfinite(blur_floor_px) and blur_floor_px >= 0):
        raise InputError("blur_floor_px", blur_floor_px, ">= 0 px and finite")
    if not (math.isfinite(floor_prior_sigma_px) and floor_prior_sigma_px > 0):
        raise InputError("floor_prior_sigma_px", floor_prior_sigma_px, "> 0 px and finite")
    pupil = _pupil_mode(pupil_magnification)
    data = prepare(samples, pixel_pitch_mm=pixel_pitch_mm, focal_length_px=focal_length_px,
                   focal_length_sigma_px=focal_length_sigma_px)
    try:
        with np.errstate(all="ignore"):  # overflow on the way is caught below, not printed
            result = _fit(data, loss, blur_floor_px, floor_prior_sigma_px, max_irls, pupil)
    except InputError:
        raise
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
        return _refused(data, loss, f"the fit failed numerically ({type(exc).__name__}: {exc}); the samples span "
                        "magnitudes no lens produces: check their units (mm, px) and the pixel pitch")
    try:
        json.dumps(result.to_json_dict(), allow_nan=False)
    except ValueError:
        return _refused(data, loss, "the fit produced non-finite numbers; the samples span magnitudes no lens "
                        "produces: check their units (mm, px) and the pixel pitch")
    return result


#: Pupil magnifications outside this range are refused (real photographic lenses: about 0.3
#: for long telephotos to about 4 for extreme retrofocus wide angles).
PUPIL_MAGNIFICATION_RANGE = (0.1, 10.0)
#: Width (1 sigma of log P) of the weak prior that keeps a fitted P in a sane range; a factor of
#: e^3 = 20 either way, so it never matters where the data determine P.
_P_PRIOR_SIGMA_LOG = 3.0
#: A fitted P needs focus settings spread enough that its relative 1 sigma stays below this;
#: up to it, P is fitted and its uncertainty widens the intervals of f and N (an assumed P = 1
#: would leave them narrow and wrong by (f/X)(1/P - 1)).
_P_MAX_RELATIVE_SIGMA = 0.3


def _pupil_mode(value) -> tuple:
    """("auto",), ("fixed", P) or ("prior", log mean, log sigma) from the ``pupil_magnification`` argument."""
    lo_ok, hi_ok = PUPIL_MAGNIFICATION_RANGE
    req = f"a number between {lo_ok:g} and {hi_ok:g}, a range (lo, hi) within it, or None"

    def number(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo_ok <= v <= hi_ok):
            raise InputError("pupil_magnification", value, req)
        return float(v)

    if value is None:
        return ("auto",)
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise InputError("pupil_magnification", value, req)
        lo, hi = number(value[0]), number(value[1])
        if not lo < hi:
            raise InputError("pupil_magnification", value, req, "give the range as (lo, hi) with lo < hi")
        return ("prior", 0.5 * (math.log(lo) + math.log(hi)), 0.25 * (math.log(hi) - math.log(lo)))
    return ("fixed", number(value))


def _p_identifiable(data: FitData, verts: np.ndarray, usable: list[int], fpx_sig: np.ndarray) -> tuple[bool, str]:
    """Whether calibrated settings ``usable`` focus far enough apart to fit P (unit focusing:
    ``1/S_k = 1/f - (1/P)(1/X_k)`` is a line in ``1/X_k``), and if not, why."""
    if len(usable) < 2:
        return False, "one calibrated focus setting cannot determine it"
    x = verts[usable]
    spread = float(np.sqrt(np.sum((x - x.mean()) ** 2)))
    inv_s = 1.0 / (data.focal_length_px[usable] * data.pixel_pitch_mm)
    sd_inv_s = float(np.max(inv_s * fpx_sig[usable] / data.focal_length_px[usable]))
    if spread <= 0 or sd_inv_s / spread > _P_MAX_RELATIVE_SIGMA:
        return False, (f"the calibrated settings focus too close together (inverse focus distances within "
                       f"{1000 * np.ptp(x):.3g} /m) to determine it; focus a bracket at distances a factor 2 or more "
                       "apart")
    return True, ""


def _p_start(data: FitData, verts: np.ndarray, usable: list[int]) -> float:
    """Closed-form P from the line ``1/S_k = 1/f - (1/P) x_k`` through the calibrated settings."""
    x = verts[usable]
    y = 1.0 / (data.focal_length_px[usable] * data.pixel_pitch_mm)
    slope = np.polyfit(x, y, 1)[0] if len(usable) >= 2 and np.ptp(x) > 0 else -1.0
    P = -1.0 / slope if slope < 0 else 1.0
    return float(min(max(P, PUPIL_MAGNIFICATION_RANGE[0]), PUPIL_MAGNIFICATION_RANGE[1]))


def _refused(data: FitData, loss: str, reason: str) -> FitResult:
    """A result that states ``reason`` for every quantity (value None; never NaN)."""
    n, m = len(data.coc_px), len(data.labels)
    none = Estimate(None, reason=reason)
    return FitResult({label: {q: none for q in QUANTITIES} for label in data.labels}, none, "not_identifiable",
                     [reason], [], np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)), math.inf, n, 0, math.nan,
                     math.nan, loss, [], data, np.zeros(n), np.ones(n), np.zeros(_size(m)))


def _fit(data: FitData, loss: str, blur_floor_px: float | None, floor_prior_sigma_px: float,
         max_irls: int, pupil: tuple) -> FitResult:
    """The body of :func:`fit` on validated data (it may raise on data of absurd magnitude;
    :func:`fit` turns that into a refusal)."""
    import jax
    import jax.numpy as jnp

    labels, m, p = data.labels, len(data.labels), data.pixel_pitch_mm
    n = len(data.coc_px)
    warnings: list[str] = []
    if data.dropped:
        warnings.append(f"{data.dropped} sample(s) without a measured blur were left out")

    # ---- what cannot be determined before fitting (per setting)
    blocked = _capture_problems(data)
    has_fpx = ~np.isnan(data.focal_length_px)
    no_fpx_reason = ("no focal length in px for this setting (calibration or stack.toml [[intrinsics]]): blur fixes "
                     "only the slope A*s and the focus distance; calibrate on tilted target views to separate f and N")

    # ---- closed-form start
    fixed_floor = blur_floor_px is not None
    theta = np.zeros(_size(m))
    i_p = 1 + 3 * m
    verts, slopes = np.zeros(m), np.ones(m)
    for k in range(m):
        sel = data.setting == k
        x, slope, b = _vertex_search(data.w_mean[sel], data.coc_px[sel], data.sigma_px[sel], np.ones(sel.sum()),
                                     not fixed_floor, blur_floor_px or 0.0)
        verts[k], slopes[k] = x, max(slope, 1e-6)
        theta[1 + 2 * m + k] = blur_floor_px if fixed_floor else max(b, 0.3)

    # ---- the pupil magnification: fitted, given a prior, or assumed (never silently)
    fpx_sig = np.where(data.focal_length_sigma_px > 0, data.focal_length_sigma_px, 1e-7 * data.focal_length_px)
    usable = [k for k in range(m) if has_fpx[k] and k not in blocked]
    p_prior = (0.0, 0.0)
    if pupil[0] == "fixed":
        P0, p_source = pupil[1], "assumed"
    elif pupil[0] == "prior":
        P0, p_source, p_prior = math.exp(pupil[1]), "prior", (pupil[1], 1.0 / pupil[2])
    else:
        fit_p, why_not = _p_identifiable(data, verts, usable, fpx_sig)
        if fit_p:
            P0, p_source, p_prior = _p_start(data, verts, usable), "fitted", (0.0, 1.0 / _P_PRIOR_SIGMA_LOG)
        else:
            P0, p_source = 1.0, "assumed"
            if has_fpx.any():
                warnings.append(f"pupil magnification P = 1 assumed (a thin lens): {why_not}. A real lens has P "
                                "about 0.5-0.9 (telephoto) to 1.2-2.5 (retrofocus wide angle), which moves f and N "
                                "by about (f/X)(1/P - 1); give pupil_magnification (--pupil-magnification) as a "
                                "value or a range, or add a second focus setting")
    theta[i_p] = math.log(P0)

    f_guess = [1 / (1 / (data.focal_length_px[k] * p) + verts[k] / P0) for k in range(m)
               if has_fpx[k] and k not in blocked]
    f_guess = f_guess or [1 / (1 / (data.focal_length_px[k] * p) + verts[k] / P0) for k in range(m) if has_fpx[k]]
    f0 = float(np.median(f_guess)) if f_guess else 50.0
    theta[0] = math.log(f0)
    for k in range(m):
        x = min(verts[k], 0.9 * P0 / f0)
        s = 1 / (1 / f0 - x / P0)
        theta[1 + k] = 1000 * x
        theta[1 + m + k] = math.log(f0 * s / (slopes[k] * p))

    # ---- free parameters
    free = np.ones(_size(m), bool)
    free[i_p] = p_source != "assumed"
    if not any(has_fpx[k] and k not in blocked for k in range(m)):
        # Without a calibrated setting whose V is determined, f only scales N: held at a
        # nominal value and reported as unknown.
        free[0] = False
    for k in blocked:
        free[[1 + k, 1 + m + k, 1 + 2 * m + k]] = False
    if fixed_floor:
        free[1 + 2 * m:1 + 3 * m] = False
    free_idx = np.flatnonzero(free)

    fpx = np.where(has_fpx, data.focal_length_px, 0.0)
    fpx_sig = np.where(has_fpx, fpx_sig, 0.0)
    fpx_w = np.where(has_fpx, 1.0 / np.maximum(fpx_sig, 1e-300), 0.0)
    floor_w = np.where(fixed_floor, 0.0, 1.0 / floor_prior_sigma_px) * np.ones(m)
    for k in blocked:
        fpx_w[k] = 0.0
        floor_w[k] = 0.0
    # Blocked settings leave the blur rows out (their parameters are held).
    row_on = np.array([data.setting[i] not in blocked for i in range(n)], float)

    npad = _padded_size(n)
    fn = _solver_residual_fn(m)
    rounds = 0 if not free_idx.size else 1 if loss == "linear" else max(1, max_irls)

    def irls(theta, rows, weights):
        """Levenberg-Marquardt inside iteratively reweighted least squares over the blur rows
        ``rows`` (0/1 per sample); returns (theta, weights, converged)."""
        theta, converged = theta.copy(), True
        for it in range(rounds):
            args = _solver_args(theta, free_idx, data, np.sqrt(weights) * rows / data.sigma_px, fpx, fpx_w, floor_w,
                                p_prior)
            sol, ok = _solver(m)[0](jnp.asarray(theta[free_idx]), args)
            sol = np.asarray(sol)
            if not np.all(np.isfinite(sol)):
                return theta, weights, False
            change = np.max(np.abs(sol - theta[free_idx])) if it else np.inf
            theta[free_idx] = sol
            converged = bool(ok)
            if loss == "linear":
                break
            u = (data.coc_px - _predict_all(theta, m, data)) / data.sigma_px
            new = _robust_weights(u / _robust_scale(u[rows > 0]), loss)
            if it and change < 1e-9 and np.max(np.abs(new - weights)) < 1e-6:
                break
            weights = new
        return theta, weights, converged

    with jax.enable_x64(True):
        theta, weights, converged = irls(theta, row_on, np.ones(n))
        # Residuals and Jacobian with the final weights.
        args = _solver_args(theta, free_idx, data, np.sqrt(weights) * row_on / data.sigma_px, fpx, fpx_w, floor_w,
                            p_prior)
        if free_idx.size:
            res, jac = (np.asarray(a) for a in _solver(m)[1](jnp.asarray(theta[free_idx]), args))
        else:
            res = np.asarray(fn(jnp.asarray(theta[free_idx]), args))
            jac = np.zeros((len(res), 0))
    if not converged:
        warnings.append("Levenberg-Marquardt stopped before its tolerance; estimates may be imprecise")

    pred = _predict_all(theta, m, data)
    resid = data.coc_px - pred
    used = row_on > 0
    u = resid / data.sigma_px
    n_used = int(used.sum())
    dof = max(float(np.sum(weights[used])) - len(free_idx), 1.0)
    chi2_red = float(np.sum(res[:npad] ** 2) / dof) if n_used else 1.0
    scale2 = max(1.0, chi2_red)
    n_out = int(np.sum(np.abs(u[used]) > 5 * math.sqrt(scale2)))

    # ---- covariance, condition, correlations
    names = _parameter_names(labels)
    fnames = [names[i] for i in free_idx]
    cov, cond, corr = _covariance(jac, scale2)
    z = (1.0, _Z95)
    if free_idx.size and np.all(data.group[used] >= 0) and MIN_CLUSTERS <= len(np.unique(data.group[used])) \
            <= MAX_CLUSTERS:
        # Leave-one-image-out jackknife: the edges of one image share its pose (distance errors
        # of ~0.05 % move all of them together) and its noise pattern, so they are not
        # independent samples and the model-based covariance understates the spread (seen:
        # focus-distance intervals holding the truth in 67 % of ray-traced stacks instead of
        # 95 %). Each image is dropped in turn (zero weight, same compiled solver) and the fit
        # redone from the solution with the robust weights held; a parameter's variance is the
        # larger of the two estimates.
        groups = np.unique(data.group[used])
        with jax.enable_x64(True):
            refits = []
            for g in groups:  # one LM solve each, robust weights held (cheap: no recompilation)
                args = _solver_args(theta, free_idx, data, np.sqrt(weights) * row_on * (data.group != g)
                                    / data.sigma_px, fpx, fpx_w, floor_w, p_prior)
                refits.append(np.asarray(_solver(m)[0](jnp.asarray(theta[free_idx]), args)[0]))
        refits = np.array(refits)
        G = len(groups)
        spread_cov = (G - 1) * np.cov(refits.T, bias=True).reshape(len(free_idx), len(free_idx))
        if np.all(np.isfinite(spread_cov)):
            sd = np.sqrt(np.maximum(np.diag(cov), np.diag(spread_cov)))
            if np.any(np.diag(spread_cov) > np.diag(cov)):
                # A jackknife over G images has G - 1 degrees of freedom: Student-t intervals.
                from scipy.stats import t as student

                z = (float(student.ppf(0.8413447460685429, G - 1)), float(student.ppf(0.975, G - 1)))
            cov = corr * np.outer(sd, sd)
    full_cov = np.zeros((_size(m), _size(m)))
    full_cov[np.ix_(free_idx, free_idx)] = cov

    degenerate = cond > MAX_CONDITION
    weak: set[str] = set()
    if degenerate and len(free_idx):
        # The parameters in the near-null direction are the ones that cannot be told apart.
        js = _null_direction(jac)
        weak = {fnames[i] for i in range(len(fnames)) if abs(js[i]) > 0.3}

    # ---- a second, distinct V that fits about as well (discrete ambiguity the covariance misses)
    for k, label in enumerate(labels):
        if k in blocked:
            continue
        sel = data.setting == k
        grid, chi2, _, _ = _vertex_profile(data.w_mean[sel], data.coc_px[sel], data.sigma_px[sel], weights[sel],
                                           not fixed_floor, blur_floor_px or 0.0)
        x_fit = theta[1 + k] / 1000.0
        sd_x = math.sqrt(max(full_cov[1 + k, 1 + k], 0.0)) / 1000.0
        far = np.abs(grid - x_fit) > max(5 * sd_x, 0.02 * np.ptp(data.w_mean[sel]))
        if far.any() and chi2[far].min() < chi2.min() + 9.0 * scale2:
            alt = grid[far][np.argmin(chi2[far])]
            alt_mm = f"{1 / alt:.0f} mm" if alt > 0 else "infinity"
            blocked[k] = (f"two focus distances fit setting {label!r} about equally well ({1 / x_fit:.0f} mm and "
                          f"{alt_mm}){_side_hint(data.w_mean[sel], x_fit)}: add targets on both sides of the focus "
                          "and spread them over more distances")

    # ---- derived quantities
    settings: dict[str, dict[str, Estimate]] = {}
    reasons: list[str] = []
    thin = p_source == "assumed" and theta[i_p] == 0.0
    f_est = _derive(theta, full_cov, m, p, data, free, blocked, has_fpx, no_fpx_reason, weak, settings, reasons, z,
                    thin)
    if p_source == "assumed":
        p_est = Estimate(P0, 0.0, (P0, P0), (P0, P0),
                         "assumed (a thin lens)" if thin else "assumed (given as pupil_magnification)")
    else:
        sd_p = math.sqrt(max(full_cov[i_p, i_p], 0.0))
        p_est = _positive(math.exp(theta[i_p]), sd_p, z)
        if p_source == "fitted" and ("log_P" in weak or sd_p > MAX_RELATIVE_SIGMA):
            p_est = Estimate(None, reason=f"the pupil magnification is poorly constrained (relative 1 sigma "
                             f"{100 * sd_p:.0f}%): focus the settings farther apart")
            reasons.append(f"pupil_magnification: {p_est.reason}")
    code = "ok" if not reasons else "not_identifiable"
    return FitResult(settings, f_est, code, reasons, fnames, theta[free_idx], cov, corr, cond, n_used, n_out,
                     chi2_red, float(np.sqrt(np.mean(resid[used] ** 2))) if n_used else 0.0, loss, warnings, data,
                     resid, weights, theta.copy(),
                     dict(free_idx=free_idx, fpx=fpx, fpx_w=fpx_w, floor_w=floor_w, row_on=row_on, p_prior=p_prior),
                     p_est, p_source)


def _padded_size(n: int) -> int:
    """Samples are padded to a power of two (zero weight), so that stacks of similar size share
    one compiled solver."""
    from lensfit.estimators.edge import _bucket

    return _bucket(n, 64)


def _solver_args(theta, free_idx, data: FitData, sqrt_w_over_sigma, fpx, fpx_w, floor_w, p_prior=(0.0, 0.0)):
    """The solver's ``args`` (JAX arrays), samples padded to :func:`_padded_size`."""
    import jax.numpy as jnp

    pad = _padded_size(len(data.coc_px)) - len(data.coc_px)

    def padded(a, fill):
        return jnp.asarray(np.concatenate([a, np.full((pad, *np.shape(a)[1:]), fill)]))

    return (jnp.asarray(theta), jnp.asarray(free_idx), padded(data.setting.astype(np.int32), 0),
            padded(data.w_nodes, 1e-3), padded(data.coc_px, 1.0), padded(sqrt_w_over_sigma, 0.0),
            data.pixel_pitch_mm, jnp.asarray(fpx), jnp.asarray(fpx_w), jnp.asarray(floor_w),
            jnp.asarray(p_prior, dtype=jnp.float64))


def _solver_residual_fn(m):
    def fn(theta_free, args):
        return _residuals(theta_free, (*args[:2], m, *args[2:]))

    return fn


def _predict_all(theta: np.ndarray, m: int, data: FitData) -> np.ndarray:
    out = np.empty(len(data.coc_px))
    for k in range(m):
        sel = data.setting == k
        out[sel] = _model_np(theta, m, k, data.w_nodes[sel], data.pixel_pitch_mm)
    return out


def _parameter_names(labels: list[str]) -> list[str]:
    return (["log_f"] + [f"inv_focus_per_m[{k}]" for k in labels] + [f"log_N[{k}]" for k in labels]
            + [f"floor_px[{k}]" for k in labels] + ["log_P"])


def _covariance(jac: np.ndarray, scale2: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Covariance by SVD of the column-equilibrated Jacobian; its condition number; correlations."""
    if jac.shape[1] == 0:
        return np.zeros((0, 0)), 1.0, np.zeros((0, 0))
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    u, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    keep = sv > sv[0] * 1e-15
    inv = np.zeros_like(sv)
    inv[keep] = 1.0 / sv[keep] ** 2
    cov_scaled = (vt.T * inv) @ vt
    cov = scale2 * cov_scaled / np.outer(norms, norms)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.outer(np.where(sd > 0, sd, 1), np.where(sd > 0, sd, 1))
    return cov, cond, np.clip(corr, -1, 1)


def _null_direction(jac: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, _, vt = np.linalg.svd(jac / norms, full_matrices=False)
    return vt[-1]


def _positive(value: float, sigma_log: float, z: tuple[float, float] = (1.0, _Z95)) -> Estimate:
    """A positive quantity with its log-space sigma: intervals ``value * exp(+-z sigma_log)``."""
    z1 = math.exp(z[0] * sigma_log)
    z2 = math.exp(z[1] * sigma_log)
    return Estimate(value, value * sigma_log, (value / z1, value * z1), (value / z2, value * z2))


_FROM_SENSOR_UNKNOWN = ("not determined for a thick lens: it needs the distance from the entrance pupil to the "
                        "sensor, which blur and a pinhole calibration do not give (the focus distance is reported "
                        "from the entrance pupil)")


def _derive(theta, cov, m, p, data, free, blocked, has_fpx, no_fpx_reason, weak, settings, reasons,
            z: tuple[float, float] = (1.0, _Z95), thin: bool = True) -> Estimate:
    """Fill ``settings`` with every reported quantity; returns the shared focal length. ``z``:
    the multiples of sigma for the 68 % and 95 % intervals. ``thin``: the lens is taken as thin
    (P = 1 assumed), so the entrance pupil is the lens plane and the focus distance from the
    sensor plane is known; otherwise that distance is not determined."""
    import jax
    import jax.numpy as jnp

    with jax.enable_x64(True):
        values, grads = _solver(m)[2](jnp.asarray(theta))
        q = {k: np.asarray(v) for k, v in values.items()}
        jacs = {k: np.asarray(v) for k, v in grads.items()}

    def sd(name, k=None):
        g = jacs[name] if k is None else jacs[name][k]
        return float(math.sqrt(max(g @ cov @ g, 0.0)))

    f_val = float(q["f"])
    f_reason = None
    if not has_fpx.any():
        f_reason = "no focal length in px for any setting: " + no_fpx_reason.split(": ", 1)[1]
    elif "log_f" in weak:
        f_reason = "the focal length is degenerate with other parameters (condition number above 1e8)"
    elif sd("log_f") > MAX_RELATIVE_SIGMA:
        f_reason = (f"the focal length is poorly constrained (relative 1 sigma {100 * sd('log_f'):.0f}%): "
                    "the focus distance of the calibrated setting(s) is not located by the blur")
    elif all(k in blocked for k in range(m) if has_fpx[k]):
        f_reason = "the focal length needs the focus distance of a calibrated setting, which is not determined"
    f_est = Estimate(None, reason=f_reason) if f_reason else _positive(f_val, sd("log_f"), z)
    if f_reason:
        reasons.append(f"focal_length_mm: {f_reason}")

    for k, label in enumerate(data.labels):
        out: dict[str, Estimate] = {}
        sel = data.setting == k
        why = blocked.get(k)
        inv_d, s_inv = float(q["inv_d"][k]), sd("inv_d", k)
        w = data.w_mean[sel] * 1000.0
        w_span = float(w.max() - w.min()) if sel.any() else 0.0
        if why is None:
            name = f"inv_focus_per_m[{label}]"
            if name in weak:
                why = f"the focus distance of setting {label!r} is degenerate with other parameters"
            elif s_inv > 0.25 * max(w_span, 1e-12) and s_inv > MAX_RELATIVE_SIGMA * abs(inv_d):
                why = (f"the focus distance of setting {label!r} is poorly located (inverse distance 1 sigma "
                       f"{s_inv:.3g} /m against a sample span of {w_span:.3g} /m){_side_hint(w, inv_d)}: add targets "
                       "on the other side of the focus distance, or spread them over a wider range of distances")
        # Focus distance (lens plane) and the inverse distance.
        if why:
            for qn in QUANTITIES:
                if qn != "focal_length_mm":
                    out[qn] = Estimate(None, reason=why)
            reasons.append(f"settings.{label}: {why}")
        else:
            lo95, hi95 = inv_d - z[1] * s_inv, inv_d + z[1] * s_inv
            lo68, hi68 = inv_d - z[0] * s_inv, inv_d + z[0] * s_inv
            out["inverse_focus_distance_per_m"] = Estimate(inv_d, s_inv, (lo68, hi68), (lo95, hi95))

            def dist(lo, hi):  # an inverse-distance interval as a distance interval (None = infinity)
                return (1000.0 / hi if hi > 0 else None, 1000.0 / lo if lo > 0 else None)

            s_val = float(q["s"][k])
            if inv_d > 0:
                dval = 1000.0 / inv_d
                out["focus_distance_mm"] = Estimate(dval, dval * s_inv / inv_d, dist(lo68, hi68), dist(lo95, hi95))
                ds = out["focus_distance_mm"]
                out["focus_distance_from_sensor_mm"] = Estimate(
                    dval + s_val, ds.sigma, tuple(None if v is None else v + s_val for v in ds.ci68),
                    tuple(None if v is None else v + s_val for v in ds.ci95)) if thin else Estimate(
                    None, reason=_FROM_SENSOR_UNKNOWN)
            else:
                note = (f"focus at infinity within the uncertainty (inverse focus distance {inv_d:.3g} +- "
                        f"{s_inv:.2g} /m)")
                out["focus_distance_mm"] = Estimate(None, None, dist(lo68, hi68), dist(lo95, hi95), note, True)
                out["focus_distance_from_sensor_mm"] = (Estimate(None, None, None, None, note, True) if thin
                                                        else Estimate(None, reason=_FROM_SENSOR_UNKNOWN))
            fl = float(q["floor"][k])
            s_fl = sd("floor", k)
            out["blur_floor_px"] = Estimate(abs(fl), s_fl, (max(abs(fl) - z[0] * s_fl, 0.0), abs(fl) + z[0] * s_fl),
                                            (max(abs(fl) - z[1] * s_fl, 0.0), abs(fl) + z[1] * s_fl))
            out["blur_slope_mm2"] = _positive(float(np.exp(q["log_K"][k])), sd("log_K", k), z)
            lens_reason = None
            if f_reason:
                lens_reason = f_reason
            elif not has_fpx[k] and not has_fpx.any():
                lens_reason = no_fpx_reason
            elif sd("log_N", k) > MAX_RELATIVE_SIGMA:
                lens_reason = f"the f-number of setting {label!r} is poorly constrained ({100 * sd('log_N', k):.0f}%)"
            if lens_reason:
                for qn in ("f_number", "aperture_diameter_mm", "sensor_distance_mm"):
                    out[qn] = Estimate(None, reason=lens_reason)
                if thin and not out["focus_distance_from_sensor_mm"].infinite:
                    out["focus_distance_from_sensor_mm"] = Estimate(None, reason=lens_reason)
                reasons.append(f"settings.{label}.f_number: {lens_reason}")
            else:
                out["f_number"] = _positive(float(q["N"][k]), sd("log_N", k), z)
                out["aperture_diameter_mm"] = _positive(float(np.exp(q["log_A"][k])), sd("log_A", k), z)
                out["sensor_distance_mm"] = _positive(float(np.exp(q["log_sx"][k])), sd("log_sx", k), z)
        out["focal_length_mm"] = f_est
        settings[label] = {qn: out[qn] for qn in QUANTITIES}
    return f_est


def cramer_rao(result: FitResult, focal_length_mm: float, settings: dict[str, tuple[float, float]]
               ) -> dict[str, dict[str, float | None]]:
    """Cramer-Rao lower bound (1 sigma) on f, N and the focus distance for the capture a fit saw.

    The same samples (depths along each edge, each sample's stated sigma as its noise), the
    same calibration rows and floor prior, the Fisher information evaluated at the true
    parameters (``settings``: label -> (f-number, focus distance from the lens, mm; inf allowed))
    with no floor. The bound is what an unbiased estimator with these measurements could reach
    at best; a benchmark compares the observed scatter with it.

    Returns label -> {"focal_length_mm", "f_number", "focus_distance_mm"} -> sigma (None where
    the parameter was not free in the fit).
    """
    import jax
    import jax.numpy as jnp

    data, setup = result.samples, result._setup
    m = len(data.labels)
    theta = np.zeros(_size(m))
    theta[1 + 3 * m] = result._full[1 + 3 * m]  # P as the fit had it
    theta[0] = math.log(focal_length_mm)
    for k, label in enumerate(data.labels):
        n_true, d_true = settings[label]
        theta[1 + k] = 0.0 if math.isinf(d_true) else 1000.0 / d_true
        theta[1 + m + k] = math.log(n_true)
    free_idx = setup["free_idx"]
    with jax.enable_x64(True):
        args = _solver_args(theta, free_idx, data, setup["row_on"] / data.sigma_px, setup["fpx"], setup["fpx_w"],
                            setup["floor_w"], setup.get("p_prior", (0.0, 0.0)))
        _, jac = _solver(m)[1](jnp.asarray(theta[free_idx]), args)
        values, grads = _solver(m)[2](jnp.asarray(theta))
    cov_free, _, _ = _covariance(np.asarray(jac), 1.0)
    cov = np.zeros((_size(m), _size(m)))
    cov[np.ix_(free_idx, free_idx)] = cov_free

    def sd(name, k=None):
        g = np.asarray(grads[name]) if k is None else np.asarray(grads[name])[k]
        return float(math.sqrt(max(g @ cov @ g, 0.0)))

    out = {}
    for k, label in enumerate(data.labels):
        free_here = {1 + k, 1 + m + k} <= set(int(i) for i in free_idx)
        v = float(np.asarray(values["inv_d"])[k])
        out[label] = {
            "focal_length_mm": focal_length_mm * sd("log_f") if 0 in free_idx else None,
            "f_number": settings[label][0] * sd("log_N", k) if free_here else None,
            "focus_distance_mm": (1000.0 * sd("inv_d", k) / v**2 if v > 0 else None) if free_here else None,
        }
    return out


# --------------------------------------------------------------------------- files


def results_document(result: FitResult, command: Iterable[str] | None = None,
                     truth: dict[str, Any] | None = None, intrinsics: dict[str, Any] | None = None) -> dict[str, Any]:
    """The results JSON with provenance (and, when given, the truth and relative errors, and the
    geometric calibration per setting: ``intrinsics`` maps a label to
    ``lensfit.calibration.Intrinsics``)."""
    import datetime
    import platform

    from lensfit import __version__

    doc = result.to_json_dict()
    doc["provenance"] = {"program": "lensfit", "version": __version__,
                         "command": " ".join(command) if command else None,
                         "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                         "python": platform.python_version(), "machine": platform.machine()}
    if intrinsics:
        doc["calibration"] = {
            label: {"focal_length_px": v.focal_length_px, "focal_length_sigma_px": v.focal_length_sigma_px,
                    "principal_point_px": list(v.principal_point_px),
                    "distortion_opencv": [float(x) for x in v.distortion], "rms_px": v.rms_px, "views": v.views,
                    "source": v.source}
            for label, v in intrinsics.items()}
    if truth is not None:
        doc["truth_comparison"] = compare_with_truth(result, truth)
    return doc


def compare_with_truth(result: FitResult, truth: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows (setting, quantity, estimate, sigma, truth, relative error, within 95 %) for the
    quantities ``truth.json`` states (data_specs/schemas/truth.schema.json)."""
    rows = []
    true_f = truth.get("focal_length_mm")
    for label, qs in result.settings.items():
        t = truth.get("settings", {}).get(label, {})
        for qn, tv in (("focal_length_mm", true_f), *((q, t.get(q)) for q in (
                "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm", "sensor_distance_mm",
                "aperture_diameter_mm"))):
            if tv is None or qn not in qs:
                continue
            e = qs[qn]
            tv = float(tv)
            rel = None if e.value is None or not math.isfinite(tv) else e.value / tv - 1
            inside = None
            if e.ci95 is not None:
                lo, hi = e.ci95
                inside = (lo is None or lo <= tv) and (hi is None or tv <= hi)
            rows.append({"setting": label, "quantity": qn, "estimate": e.value, "sigma": e.sigma,
                         "truth": tv if math.isfinite(tv) else None, "relative_error": rel, "within_ci95": inside,
                         "infinite": e.infinite})
    return rows


def write_results(path: str | Path, document: dict[str, Any]) -> None:
    """Write atomically (a temporary sibling, then rename); finite numbers or null only."""
    from lensfit.outputs import write_text

    write_text(path, json.dumps(document, indent=1, allow_nan=False))


__all__ = ["fit", "cramer_rao", "FitResult", "Estimate", "FitData", "prepare", "inverse_distance_moments", "results_document",
           "compare_with_truth", "write_results", "QUANTITIES", "LOSSES"]
