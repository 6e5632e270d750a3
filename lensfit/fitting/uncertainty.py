"""Covariance, the delta method to every reported quantity, and the Cramer-Rao bound."""

from __future__ import annotations

import math

import numpy as np

from lensfit.fitting.constants import MAX_CLUSTERS, MAX_RELATIVE_SIGMA, MIN_CLUSTERS, QUANTITIES, Z95
from lensfit.fitting.model import Layout, vector_size
from lensfit.fitting.result import Estimate, FitResult
from lensfit.fitting.solve import solver_for, solver_args
from lensfit.fitting.start import side_hint


def svd_covariance(jac: np.ndarray, scale2: float) -> tuple[np.ndarray, float]:
    """Covariance by SVD of the column-equilibrated Jacobian; its condition number."""
    if jac.shape[1] == 0:
        return np.zeros((0, 0)), 1.0
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    u, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    keep = sv > sv[0] * 1e-15
    inv = np.zeros_like(sv)
    inv[keep] = 1.0 / sv[keep] ** 2
    cov_scaled = (vt.T * inv) @ vt
    return scale2 * cov_scaled / np.outer(norms, norms), cond


def correlation(cov: np.ndarray) -> np.ndarray:
    """Correlations of a covariance (0 in the rows of a parameter without variance)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sd = np.where(sd > 0, sd, 1.0)
    return np.clip(cov / np.outer(sd, sd), -1.0, 1.0)


#: The sources a reported variance is split into (results.json ``variance_shares``): the
#: blur readings' own scatter ("blur"); the calibrated focal length in px and with it the scale
#: of every pose distance ("calibration"); what the edges of one image share beyond that (its
#: pose, its noise: :func:`images_part`, and the excess of the images' spread, :func:`image_spread`;
#: "images"); the blur
#: estimator's shared scale error ("estimator_scale", ``BLUR_SCALE_SIGMA``); the spot-shape
#: model's error on each side of the focus (:func:`arms_part`, "spot_shape"); the priors on the
#: blur floor and the pupil magnification ("priors"). (A one-sided setting's "floor_choice" is
#: added after the fit: lensfit.fitting.refits.)
BUDGET_SOURCES = ("blur", "calibration", "images", "estimator_scale", "spot_shape", "priors")


def budget_parts(jac: np.ndarray, cov: np.ndarray, npad: int, m: int) -> dict[str, np.ndarray]:
    """The model covariance of the free parameters split by the rows that carry it:
    ``H^-1 J_g^T J_g H^-1`` for each row group ``g`` (``H = J^T J``, ``cov = H^-1``), which sum
    to ``H^-1``. Rows (``jac`` as weighted for the covariance): blur samples (``npad``), the focal
    lengths in px (``m``), then the priors."""
    if jac.shape[1] == 0:
        return {}
    groups = {"blur": slice(0, npad), "calibration": slice(npad, npad + m), "priors": slice(npad + m, None)}
    return {name: cov @ jac[sl].T @ jac[sl] @ cov for name, sl in groups.items()}


def images_part(jac: np.ndarray, cov_u: np.ndarray, data, rows: np.ndarray, scatter) -> np.ndarray:
    """The free parameters' covariance from the images' shared distance errors:
    ``sum_i b_i b_i'``, ``b_i = H^-1 J_i' (g_i sqrt(w_i) / sigma_i) tau`` (``jac`` the weighted
    Jacobian of the fit, blur rows first in sample order, ``H = J' J``, ``cov_u`` its ``H^-1``;
    ``rows`` the samples' weights in it; ``scatter``: :class:`lensfit.fitting.solve.ImageScatter`, whose ``tau`` is each
    image's relative distance error, pooled over the images). An image's pose error moves all of
    its edges' blur together, which the blur rows, taken as independent, do not carry."""
    p = jac.shape[1]
    out = np.zeros((p, p))
    if p == 0 or scatter is None or scatter.tau <= 0:
        return out
    n = len(data.coc_px)
    pose = scatter.slope * np.sqrt(rows) / data.sigma_px * scatter.tau
    for g in np.unique(data.group[(rows > 0) & (data.group >= 0)]):
        sel = (data.group == g) & (rows > 0)
        b = cov_u @ (jac[:n][sel].T @ pose[sel])
        out += np.outer(b, b)
    return out


def arms_part(jac: np.ndarray, cov_u: np.ndarray, data, rows: np.ndarray, theta: np.ndarray,
               m: int) -> np.ndarray:
    """The free parameters' covariance from the spot-shape model's error on each side of each
    setting's focus: ``sum b b'``, ``b = H^-1 J_arm' (c sqrt(w) / sigma) kappa`` over the samples
    of one arm (``jac``, ``cov_u``, ``rows`` as in :func:`images_part`).

    A real lens's spots differ in kind on the two sides of its focus (a bright rim on one, a core
    in a halo on the other, coma off the axis), and a symmetric spot model misreads one kind more
    than the other: every reading of that arm by the same share, which tilts the V, moving its
    vertex (the focus distance) as well as its slope (N). The share is not known, but its size
    is shown by the arm's own edges: ``kappa`` is ``SPOT_SHAPE_SHARE`` times the median relative
    difference between the shaped reading and the uniform disk's of the same edge over the arm
    (``FitData.disk_px``); 0 on an arm without shaped readings, a few tenths of a percent on
    uniform disks. Measured on exact edges of real-ray spots: the shaped reading's error ran from
    a tenth of that difference (a retrofocus's cores in a halo) to twice it (an f/1.4 Petzval's
    comatic spots 200 px off the axis), so a 1 sigma of once the difference."""
    p = jac.shape[1]
    out = np.zeros((p, p))
    if p == 0:
        return out
    n = len(data.coc_px)
    at = Layout(m)
    # each sample's in-focus inverse distance (1/mm): its setting's, moved by the field curvature
    vertex = (theta[at.inv_focus_per_m()][data.setting] + theta[at.curvature()][data.setting]
              * np.nan_to_num(np.asarray(data.field2, float))) / 1000.0
    near = data.w_mean > vertex
    on = rows > 0
    lever = data.coc_px * np.sqrt(rows) / data.sigma_px
    error = np.asarray(data.shape_error, float)
    for k in range(m):
        for arm in (near, ~near):
            sel = on & arm & (data.setting == k)
            shaped = sel & np.isfinite(error)
            if not shaped.any():
                continue
            kappa = float(np.mean(error[shaped]))
            b = cov_u @ (jac[:n][sel].T @ (lever[sel] * kappa))
            out += np.outer(b, b)
    return out


def shares_of(model: dict[str, float], reported_var: float) -> dict[str, float] | None:
    """Shares of a reported variance: ``model`` the parts the model covariance carries (and the
    estimator's scale term), the rest of ``reported_var``, the images' spread's excess, added to
    ``images``."""
    v = dict(model)
    v["images"] = v.get("images", 0.0) + max(reported_var - sum(v.values()), 0.0)
    total = sum(v.values())
    return {src: v.get(src, 0.0) / total for src in BUDGET_SOURCES} if total > 0 else None


def null_direction(jac: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, _, vt = np.linalg.svd(jac / norms, full_matrices=False)
    return vt[-1]


def focus_interval(lo_per_m: float, hi_per_m: float) -> tuple[float | None, float | None]:
    """An inverse focus distance interval (per m) as a focus distance interval (mm; None: infinity)."""
    return (1000.0 / hi_per_m if hi_per_m > 0 else None, 1000.0 / lo_per_m if lo_per_m > 0 else None)


def positive_estimate(value: float, sigma_log: float, z: tuple[float, float] = (1.0, Z95)) -> Estimate:
    """A positive quantity with its log-space sigma: intervals ``value * exp(+-z sigma_log)``."""
    z1 = math.exp(z[0] * sigma_log)
    z2 = math.exp(z[1] * sigma_log)
    return Estimate(value, value * sigma_log, (value / z1, value * z1), (value / z2, value * z2))


class StrataDof:
    """Degrees of freedom of the images' stratified spread (Satterthwaite): ``parts`` the
    strata's covariance contributions (full size), ``dofs`` their images less one. A quantity of
    gradient ``g`` gets ``(sum v_h)^2 / sum(v_h^2 / dof_h)``, ``v_h = g' V_h g``: a quantity of one
    setting of a focus bracket counts that setting's images only."""

    def __init__(self, parts: list[np.ndarray], dofs: list[float]):
        self.parts, self.dofs = parts, dofs
        self.total = float(sum(dofs))

    def of(self, g: np.ndarray) -> float:
        v = [max(float(g @ P @ g), 0.0) for P in self.parts]
        den = sum(vh * vh / dh for vh, dh in zip(v, self.dofs))
        return sum(v) ** 2 / den if den > 0 else math.inf


def image_spread(cov, blur_cov, jac, res, cov_fit, free_idx, data, used):
    """The images' spread: the edges of one image share its pose (distance errors of ~0.05 %
    move all of them together) and its noise pattern, so they are not independent samples and
    the model-based covariance understates the spread (seen: focus-distance intervals holding the
    truth in 67 % of ray-traced stacks instead of 95 %). The cluster-robust covariance with each
    image a cluster, in its bias-reduced form (CR2, Bell and McCaffrey 2002): ``sum_g b_g b_g'``,
    ``b_g = H^-1 J_g' (I - H_gg)^-1/2 r_g``, from the fit's weighted Jacobian ``jac`` (``J``,
    blur rows first in sample order), its weighted residuals ``res`` (``r``, the robust weights
    held), ``cov_fit`` = ``H^-1`` = ``(J'J)^-1``, ``J_g`` and ``r_g`` the rows of image ``g``'s
    samples and ``H_gg = J_g H^-1 J_g'`` their leverage. Unbiased where the readings are
    independent with equal variance, and consistent where an image's readings share an error.
    Stratified by setting (an image belongs to one, that of most of its samples): a stratum's
    part is the sum over its images. The calibration's rows and the priors stay in ``H`` as they
    are, so the spread is that of the blur readings alone: a parameter's blur variance is the
    larger of the model's (``blur_cov``, the blur rows' part of ``cov``) and this spread, and the
    calibration's and the priors' parts are added to it. Not called where the model carries the
    images' shared distance errors (:func:`images_part`, from their scatter pooled over all the
    images; ``lensfit.fitting.core``), whose covariance is left as it is: that term reads
    the same variance with far fewer degrees of freedom lost to the few images that carry a
    parameter. In Monte Carlo captures with per-image pose errors (10 images of 0.3 % pose errors,
    300-400 draws) this spread read the focus distance's variance 0.58x on average (the one image
    near the focus plane, leverage 0.58, carries most of it: Bell and McCaffrey's degrees of
    freedom for it are 2) and N's 1.44x, where the term reads 1.00x and 1.13x.

    CR2 rather than a leave-one-image-out jackknife (CR3, ``(I - H_gg)^-1`` for the root): the
    jackknife overstates the variance wherever an image carries much of a parameter, as each of a
    focus bracket's five images per setting does (its sigmas 1.5-2x the model's there). The
    spread is stratified by setting, so that a bracket's per-setting quantities count their own
    setting's images in their degrees of freedom, and the calibration's part is added to it.

    Unchanged where there are too few or too many images. Returns (cov, strata): ``strata``
    (each setting's share of the spread, free size, and its images less one) where the spread
    took over for some parameter, else None; each reported quantity's intervals take their
    degrees of freedom from them (:class:`StrataDof`, :func:`effective_z`)."""
    if not (free_idx.size and np.all(data.group[used] >= 0)
            and MIN_CLUSTERS <= len(np.unique(data.group[used])) <= MAX_CLUSTERS):
        return cov, None
    groups = np.unique(data.group[used])
    b = np.zeros((len(groups), len(free_idx)))
    stratum = np.zeros(len(groups), int)  # each image's: the setting of most of its samples
    for i, g in enumerate(groups):
        rows = np.flatnonzero(used & (data.group == g))
        stratum[i] = np.bincount(data.setting[rows]).argmax()
        jg = jac[rows]
        lev, vec = np.linalg.eigh(np.eye(len(rows)) - jg @ cov_fit @ jg.T)
        # (I - H_gg)^-1/2 r_g; a direction the image alone determines (1 - leverage ~ 0) has no residual
        root = np.where(lev > 1e-9, 1.0 / np.sqrt(np.maximum(lev, 1e-9)), 0.0)
        b[i] = cov_fit @ (jg.T @ (vec @ (root * (vec.T @ res[rows]))))
    strata = [(b[stratum == h].T @ b[stratum == h], float(np.sum(stratum == h) - 1))
              for h in np.unique(stratum) if np.sum(stratum == h) >= 2]
    spread_cov = sum((c for c, _ in strata), np.zeros((len(free_idx), len(free_idx))))
    if not strata or not np.all(np.isfinite(spread_cov)):
        return cov, None
    model, spread = np.maximum(np.diag(blur_cov), 0.0), np.diag(spread_cov)
    corr = correlation(blur_cov)
    np.fill_diagonal(corr, 1.0)
    sd = np.sqrt(np.maximum(model, spread))
    cov = cov - blur_cov + corr * np.outer(sd, sd)
    return cov, (strata if np.any(spread > model) else None)


def student_z(dof: float) -> tuple[float, float]:
    """The multiples of sigma for 68.27 % and 95 % intervals, Student's t with ``dof`` degrees of
    freedom (normal where infinite)."""
    if not math.isfinite(dof):
        return (1.0, Z95)
    from scipy.special import stdtrit  # Student-t quantiles (scipy.stats takes 0.6-1.2 s to import)

    return (float(stdtrit(dof, 0.8413447460685429)), float(stdtrit(dof, 0.975)))


def effective_z(shares: dict[str, float] | None, dof: float, blur_dof: float = math.inf,
                images_dof: float = math.inf, calibration_den: float = 0.0) -> tuple[float, float]:
    """The interval multiples for one reported quantity whose variance is partly estimated from
    the data and partly known in form (the calibration, the estimator's scale error, the priors:
    infinitely many degrees of freedom): Student's t with the Welch-Satterthwaite effective
    degrees of freedom (GUM, JCGM 100:2008 G.4) ``nu = nu_0 / r^2``, ``r`` the estimated share
    of the variance. Where the images' spread took over for the quantity (``images`` > 0 in
    ``shares``), that share is ``blur`` + ``images`` with ``nu_0 = dof``, the spread's (its
    images less one, or for a quantity of a bracket's setting, :class:`StrataDof`); elsewhere it is
    ``blur``, whose size the readings' own scatter about the fit sets (the reduced chi-square,
    ``nu_0 = blur_dof``: samples less free parameters), with the images' modelled share
    (:func:`images_part`) at ``images_dof``, the images less one. A calibration's part whose
    sigma a jackknife over few views estimated adds ``calibration_den``, the sum of its settings'
    ``r_k^2 / nu_k`` (views less one), to the denominator ``sum r^2 / nu``; other calibrations
    count as known, so a focal length known mostly from the calibration is not given the images'
    few degrees of freedom."""
    if not shares:
        return student_z(dof)
    if shares.get("images", 0.0) > 0 and math.isfinite(dof):
        den = (shares.get("blur", 0.0) + shares.get("images", 0.0)) ** 2 / dof + calibration_den
    else:
        den = shares.get("blur", 0.0) ** 2 / blur_dof + shares.get("images", 0.0) ** 2 / images_dof + calibration_den
    return student_z(1.0 / den) if den > 0 else (1.0, Z95)


_FROM_SENSOR_UNKNOWN = ("not determined for a thick lens: it needs the distance from the entrance pupil to the "
                        "sensor, which blur and a pinhole calibration do not give (the focus distance is reported "
                        "from the entrance pupil)")


#: Reported quantity -> the solver quantity whose variance it carries.
_CARRIER = {"focal_length_mm": "log_f", "f_number": "log_N", "focus_distance_mm": "inv_focus_per_m",
            "focus_distance_from_sensor_mm": "inv_focus_per_m", "inverse_focus_distance_per_m": "inv_focus_per_m",
            "sensor_distance_mm": "log_sx", "aperture_diameter_mm": "log_A", "blur_slope_mm2": "log_K",
            "blur_floor_px": "floor"}


class _Variance:
    """Variances of the solver's derived quantities (delta method), the estimator's shared
    scale error added where it acts, and their split into ``BUDGET_SOURCES``."""

    def __init__(self, q, jacs, cov, parts, scale_var):
        self.q, self.jacs, self.cov, self.parts, self.scale_var = q, jacs, cov, parts, scale_var

    def _grad(self, name, k):
        return self.jacs[name] if k is None else self.jacs[name][k]

    def _scale_term(self, name, k):
        """Variance from the shared blur scale: it multiplies A, the slope and the floor."""
        if name in ("log_N", "log_A", "log_K"):
            return self.scale_var
        if name == "floor":
            return self.scale_var * float(self.q["floor"][k]) ** 2
        return 0.0

    def var(self, name, k=None) -> float:
        g = self._grad(name, k)
        return max(float(g @ self.cov @ g), 0.0) + self._scale_term(name, k)

    def sd(self, name, k=None) -> float:
        return math.sqrt(self.var(name, k))

    def shares(self, name, k=None) -> dict[str, float] | None:
        if not self.parts:
            return None
        g = self._grad(name, k)
        v = {src: max(float(g @ c @ g), 0.0) for src, c in self.parts.items()}
        v["estimator_scale"] = self._scale_term(name, k)
        return shares_of(v, self.var(name, k))


def derive_quantities(theta, cov, m, p, data, free, blocked, has_fpx, no_fpx_reason, weak,
            dof: float | StrataDof = math.inf, thin: bool = True, parts=None, scale_var: float = 0.0,
            blur_dof: float = math.inf, images_dof: float = math.inf, calibration_terms=()
            ) -> tuple[dict[str, dict[str, Estimate]], list[str], Estimate]:
    """Every reported quantity: (per setting its estimates, the reasons of what is refused, the
    shared focal length). ``dof``: the images' spread's degrees of freedom where it took over
    (:func:`image_spread`; per quantity from its strata, :class:`StrataDof`), from which each
    quantity's multiples of sigma for its 68 % and 95 % intervals (:func:`effective_z`).
    ``thin``: the lens is taken as thin (P = 1 assumed), so the entrance pupil is the lens plane
    and the focus distance from the sensor plane is known; otherwise that distance is not
    determined. ``parts``: the model covariance split by source (:func:`budget_parts`, full
    size); ``scale_var``: the variance of the estimator's shared relative scale error;
    ``blur_dof``: the degrees of freedom of the blur readings' scatter (samples less free
    parameters), which sets their part of the variance."""
    import jax

    with jax.enable_x64(True):
        values, grads = solver_for(m).derived(np.asarray(theta, np.float64))
        q = {k: np.asarray(v) for k, v in values.items()}
        jacs = {k: np.asarray(v) for k, v in grads.items()}
    variance = _Variance(q, jacs, cov, parts or {}, scale_var)

    def zs(name, k=None):
        g, total = variance._grad(name, k), variance.var(name, k)
        nu = dof.of(g) if isinstance(dof, StrataDof) else dof
        cal = (sum((max(float(g @ c @ g), 0.0) / total) ** 2 / d for c, d in calibration_terms)
               if total > 0 else 0.0)
        return effective_z(variance.shares(name, k), nu, blur_dof, images_dof, cal)

    sd = variance.sd
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
    f_est = Estimate(None, reason=f_reason) if f_reason else positive_estimate(float(q["f"]), sd("log_f"), zs("log_f"))
    f_est = _with_shares(f_est, variance.shares("log_f"))
    settings: dict[str, dict[str, Estimate]] = {}
    reasons = [f"focal_length_mm: {f_reason}"] if f_reason else []
    for k, label in enumerate(data.labels):
        out, why = _setting_estimates(k, label, q, sd, zs, data, blocked, weak, thin,
                                      f_reason or _lens_reason(k, label, sd, has_fpx, no_fpx_reason))
        reasons += why
        out["focal_length_mm"] = f_est
        settings[label] = {qn: out[qn] if qn == "focal_length_mm" else _with_shares(out[qn], variance.shares(
            _CARRIER[qn], k)) for qn in QUANTITIES}
    return settings, reasons, f_est


def _lens_reason(k: int, label: str, sd, has_fpx: np.ndarray, no_fpx_reason: str) -> str | None:
    """Why setting ``k``'s f-number (and aperture, sensor distance) cannot be reported, or None."""
    if not has_fpx[k] and not has_fpx.any():
        return no_fpx_reason
    if sd("log_N", k) > MAX_RELATIVE_SIGMA:
        return f"the f-number of setting {label!r} is poorly constrained ({100 * sd('log_N', k):.0f}%)"
    return None


def _setting_estimates(k: int, label: str, q: dict, sd, zs, data, blocked: dict, weak: set, thin: bool,
                       lens_reason: str | None) -> tuple[dict[str, Estimate], list[str]]:
    """One setting's estimates (its focus distance from the lens and the sensor, blur floor and
    slope, f-number, aperture and sensor distance) and the reasons of those refused."""
    out: dict[str, Estimate] = {}
    reasons: list[str] = []
    sel = data.setting == k
    why = blocked.get(k)
    inv_focus_per_m, s_inv = float(q["inv_focus_per_m"][k]), sd("inv_focus_per_m", k)
    w = data.w_mean[sel] * 1000.0
    w_span = float(w.max() - w.min()) if sel.any() else 0.0
    if why is None:
        name = f"inv_focus_per_m[{label}]"
        if name in weak:
            why = f"the focus distance of setting {label!r} is degenerate with other parameters"
        elif s_inv > 0.25 * max(w_span, 1e-12) and s_inv > MAX_RELATIVE_SIGMA * abs(inv_focus_per_m):
            why = (f"the focus distance of setting {label!r} is poorly located (inverse distance 1 sigma "
                   f"{s_inv:.3g} /m against a sample span of {w_span:.3g} /m)"
                   f"{side_hint(w, inv_focus_per_m)}: add targets "
                   "on the other side of the focus distance, or spread them over a wider range of distances")
    # Focus distance (lens plane) and the inverse distance.
    if why:
        for qn in QUANTITIES:
            if qn != "focal_length_mm":
                out[qn] = Estimate(None, reason=why)
        return out, [f"settings.{label}: {why}"]
    z = zs("inv_focus_per_m", k)
    lo95, hi95 = inv_focus_per_m - z[1] * s_inv, inv_focus_per_m + z[1] * s_inv
    lo68, hi68 = inv_focus_per_m - z[0] * s_inv, inv_focus_per_m + z[0] * s_inv
    out["inverse_focus_distance_per_m"] = Estimate(inv_focus_per_m, s_inv, (lo68, hi68), (lo95, hi95))

    s_val = float(q["s"][k])
    if inv_focus_per_m > 0:
        dval = 1000.0 / inv_focus_per_m
        out["focus_distance_mm"] = Estimate(dval, dval * s_inv / inv_focus_per_m, focus_interval(lo68, hi68),
                                            focus_interval(lo95, hi95))
        ds = out["focus_distance_mm"]
        out["focus_distance_from_sensor_mm"] = Estimate(
            dval + s_val, ds.sigma, tuple(None if v is None else v + s_val for v in ds.ci68),
            tuple(None if v is None else v + s_val for v in ds.ci95)) if thin else Estimate(
            None, reason=_FROM_SENSOR_UNKNOWN)
    else:
        note = (f"focus at infinity within the uncertainty (inverse focus distance {inv_focus_per_m:.3g} +- "
                f"{s_inv:.2g} /m)")
        out["focus_distance_mm"] = Estimate(None, None, focus_interval(lo68, hi68), focus_interval(lo95, hi95),
                                            note, True)
        out["focus_distance_from_sensor_mm"] = (Estimate(None, None, None, None, note, True) if thin
                                                else Estimate(None, reason=_FROM_SENSOR_UNKNOWN))
    fl = float(q["floor"][k])
    s_fl = sd("floor", k)
    z = zs("floor", k)
    out["blur_floor_px"] = Estimate(abs(fl), s_fl, (max(abs(fl) - z[0] * s_fl, 0.0), abs(fl) + z[0] * s_fl),
                                    (max(abs(fl) - z[1] * s_fl, 0.0), abs(fl) + z[1] * s_fl))
    out["blur_slope_mm2"] = positive_estimate(float(np.exp(q["log_K"][k])), sd("log_K", k), zs("log_K", k))
    if lens_reason:
        for qn in ("f_number", "aperture_diameter_mm", "sensor_distance_mm"):
            out[qn] = Estimate(None, reason=lens_reason)
        if thin and not out["focus_distance_from_sensor_mm"].infinite:
            out["focus_distance_from_sensor_mm"] = Estimate(None, reason=lens_reason)
        reasons.append(f"settings.{label}.f_number: {lens_reason}")
    else:
        out["f_number"] = positive_estimate(float(q["N"][k]), sd("log_N", k), zs("log_N", k))
        out["aperture_diameter_mm"] = positive_estimate(float(np.exp(q["log_A"][k])), sd("log_A", k), zs("log_A", k))
        out["sensor_distance_mm"] = positive_estimate(float(np.exp(q["log_sx"][k])), sd("log_sx", k), zs("log_sx", k))
    return out, reasons


def _with_shares(est: Estimate, shares: dict[str, float] | None) -> Estimate:
    import dataclasses

    return dataclasses.replace(est, shares=shares) if est.value is not None and shares else est


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

    data, setup = result.samples, result._setup
    m = len(data.labels)
    theta = np.zeros(vector_size(m))
    at = Layout(m)
    theta[at.log_p] = result._full[at.log_p]  # P as the fit had it
    theta[at.LOG_F] = math.log(focal_length_mm)
    for k, label in enumerate(data.labels):
        n_true, d_true = settings[label]
        theta[at.inv_focus_per_m(k)] = 0.0 if math.isinf(d_true) else 1000.0 / d_true
        theta[at.log_n(k)] = math.log(n_true)
    free_idx = setup["free_idx"]
    with jax.enable_x64(True):
        args = solver_args(theta, free_idx, data, setup["row_on"] / data.sigma_px, setup["fpx"], setup["fpx_w"],
                            setup["floor_w"], setup.get("p_prior", (0.0, 0.0)))
        _, jac = solver_for(m).evaluate(theta[free_idx], args)
        values, grads = solver_for(m).derived(np.asarray(theta, np.float64))
    cov_free, _ = svd_covariance(np.asarray(jac), 1.0)
    cov = np.zeros((vector_size(m), vector_size(m)))
    cov[np.ix_(free_idx, free_idx)] = cov_free

    def sd(name, k=None):
        g = np.asarray(grads[name]) if k is None else np.asarray(grads[name])[k]
        return float(math.sqrt(max(g @ cov @ g, 0.0)))

    out = {}
    for k, label in enumerate(data.labels):
        free_here = {at.inv_focus_per_m(k), at.log_n(k)} <= set(int(i) for i in free_idx)
        v = float(np.asarray(values["inv_focus_per_m"])[k])
        out[label] = {
            "focal_length_mm": focal_length_mm * sd("log_f") if 0 in free_idx else None,
            "f_number": settings[label][0] * sd("log_N", k) if free_here else None,
            "focus_distance_mm": (1000.0 * sd("inv_focus_per_m", k) / v**2 if v > 0 else None) if free_here else None,
        }
    return out
