"""The fit: validate, start, solve with robust reweighting, derive, refuse what cannot be known."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from typing import Any

import numpy as np

from lensfit.errors import InputError
from lensfit.fitting.constants import (BLUR_SCALE2_MIN, FIELD_CURVATURE_MODES, FLOOR_PRIOR_SIGMA_PX, LOSSES,
                                   MAX_CONDITION, MAX_RELATIVE_SIGMA, QUANTITIES, UNREAD_SHAPE_WARN)
from lensfit.fitting.data import FitData, prepare
from lensfit.fitting import nominal, stages
from lensfit.fitting.focusing import merge, one_setting, subset, with_lens
from lensfit.fitting.identifiability import (PHOTOGRAPHIC_P_NOTE, capture_problems, curvature_estimate, field_spread,
                                             one_sided, photographic_p_interval, pupil_mode, second_vertex)
from lensfit.fitting.model import Layout, vector_size
from lensfit.fitting.result import Estimate, FitResult, Outcome, parameter_labels, refuse_left_out
from lensfit.fitting.solve import image_scatter, padded_size, predict_all
from lensfit.fitting.refits import SPOT_SHAPE_MODES, disk_instead, floor_sensitive, widen
from lensfit.fitting.uncertainty import (StrataDof, arms_part, budget_parts, correlation, svd_covariance,
                                         derive_quantities, images_part, image_spread, null_direction,
                                         positive_estimate, shares_of, student_z)


def fit(samples: Any, *, pixel_pitch_mm: float | None = None,
        focal_length_px: float | dict[str, float] | None = None,
        focal_length_sigma_px: float | dict[str, float] | None = None,
        loss: str = "huber", blur_floor_px: float | None = None,
        floor_prior_sigma_px: float = FLOOR_PRIOR_SIGMA_PX, max_irls: int = 12,
        pupil_magnification: float | tuple[float, float] | None = None,
        field_curvature: str = "auto", spot_shape: str = "auto", floor_choice: bool = True,
        focusing: str | None = None, ideal_lens: bool | None = None,
        widest_f_number: float | None = None) -> FitResult:
    """Fit focal length, and per setting f-number and focus distance, to blur samples.

    Distances are measured from the entrance pupil (the centre a pinhole calibration finds;
    the lens plane of a thin lens). The lens may be thick: its pupil magnification
    ``P`` (exit / entrance pupil diameter) enters through ``1/S = 1/f - 1/(P X)``, where
    ``S = f_px * p`` is what the calibration measures (module notes).

    Parameters
    ----------
    samples : SampleTable or str or Path or sequence
        A :class:`~lensfit.io.samples.SampleTable`, the path of a samples JSON/CSV written
        by ``lensfit measure``, or a sequence of :class:`~lensfit.io.samples.Sample` or of
        mappings of their columns (:meth:`~lensfit.io.samples.Sample.from_row`: ``setting``,
        ``distance_mm``, ``coc_diameter_px``, ``sigma_px`` and optionally
        ``distance_start_mm``/``distance_end_mm`` (the edge's ends, for tilted edges), ``flags``
        and the other columns a samples file has)
    pixel_pitch_mm : float, optional
        Sensor pixel pitch (default: the SampleTable's)
    focal_length_px : float or dict, optional
        Calibrated focal length in px (= sensor distance / pitch), one number or
        per setting label (default: the SampleTable's intrinsics). Without it f and N cannot
        be separated and are reported as not identifiable.
    focal_length_sigma_px : float or dict, optional
        Its 1 sigma (default: the calibration's; 0 = exact)
    loss : str
        "huber" (default), "cauchy" (many outliers) or "linear"
    blur_floor_px : float, optional
        Fix the blur floor (px) instead of fitting it per setting
    floor_prior_sigma_px : float
        Width of the weak prior on a fitted floor (about 0)
    max_irls : int
        Robust solves at most (least squares, then the loss until estimates and weights settle)
    pupil_magnification : float or tuple, optional
        None (default): fitted where two or more calibrated settings focus at different distances,
        else carried over the spread of photographic lenses (a log-normal prior, median 1,
        ``identifiability.PHOTOGRAPHIC_P_SIGMA_LOG``) with a warning. A number: assumed. A range ``(lo, hi)``: a
        log-normal prior whose 95 % interval it is, which widens the intervals of f and N honestly.
    field_curvature : str
        "auto" (default), "on" or "off": fit each setting's field curvature, the in-focus inverse
        distance ``1/X + kappa tan^2(field angle)`` (X then the focus distance on the axis). "auto"
        keeps kappa only where it differs from 0 by ``FIELD_CURVATURE_Z`` sigma.
    floor_choice : bool
        Where every sample of a setting lies on one side of its focus and its floor is above 0,
        fit again without the floor and widen its intervals to span both (lensfit.fitting.refits;
        default True). The pipeline's diffraction rounds compare their own rounds instead.
    focusing : str, optional
        How the lens focuses (``lensfit.fitting.focusing``; default: the samples' ``lens``, what the
        stack's ``[lens]`` said, else "unknown"): "unknown" or "internal" fits
        each setting by itself (f per setting; P as for one setting) and notes the joint reading;
        "unit" fits the settings together, sharing f and P (a bracket then determines P).
    ideal_lens : bool, optional
        The lens has no aberrations (a renderer's thin-lens camera): its f-number is the blur's own.
        Default: the samples' ``lens`` (stack.toml ``[lens] ideal``), else False: the f-number
        and aperture diameter are the nominal ones, with the spread of real designs carried
        (``lensfit.fitting.nominal``).
    widest_f_number : float, optional
        The lens's full aperture (default: the samples' ``lens``, stack.toml ``[lens]
        widest_f_number``, else unknown): a real lens's settings then carry the designs' spread as
        far stopped down as each setting is; unknown, their spread wide open.
    spot_shape : str
        "auto" (default), "shaped" or "disk": where a sample gives two readings, take its spot's
        second moment or the uniform disk's (``disk_diameter_px``); "auto" takes the disk's on
        settings where an Airy pattern the samples were not tested for may be in the blur
        (lensfit.fitting.refits), with a warning.

    Returns
    -------
    FitResult
        ``code`` "ok" or "not_identifiable"; never NaN or inf in it.

    Raises
    ------
    InputError
        No usable sample, a bad pixel pitch, focal length, loss or floor.

    Examples
    --------
    A stack's samples (``lensfit fit`` runs :func:`lensfit.measurement.pipeline.measure_and_fit`), or rows:

    >>> from lensfit.measurement.measure import measure
    >>> result = fit(measure("out/demo"))                       # doctest: +SKIP
    >>> rows = [{"setting": "a", "distance_mm": d, "coc_diameter_px": c, "sigma_px": 0.05}
    ...         for d, c in [(500, 9.5), (700, 3.9), (1400, 2.8), (2000, 4.7), (3000, 6.3)]]
    >>> result = fit(rows, pixel_pitch_mm=0.006, focal_length_px=4188.0)   # doctest: +SKIP
    """
    if loss not in LOSSES:
        raise InputError("loss", loss, "one of: " + ", ".join(LOSSES))
    if blur_floor_px is not None and not (math.isfinite(blur_floor_px) and blur_floor_px >= 0):
        raise InputError("blur_floor_px", blur_floor_px, ">= 0 px and finite")
    if not (math.isfinite(floor_prior_sigma_px) and floor_prior_sigma_px > 0):
        raise InputError("floor_prior_sigma_px", floor_prior_sigma_px, "> 0 px and finite")
    samples, pupil_magnification, focusing, ideal_lens, widest_f_number = with_lens(
        samples, pupil_magnification, focusing, ideal_lens, widest_f_number)
    pupil = pupil_mode(pupil_magnification)
    if field_curvature not in FIELD_CURVATURE_MODES:
        raise InputError("field_curvature", field_curvature, "one of: " + ", ".join(FIELD_CURVATURE_MODES))
    if spot_shape not in SPOT_SHAPE_MODES:
        raise InputError("spot_shape", spot_shape, "one of: " + ", ".join(SPOT_SHAPE_MODES))

    def run(disk_readings: Any, floor: float | None = blur_floor_px) -> FitResult:
        data = prepare(samples, pixel_pitch_mm=pixel_pitch_mm, focal_length_px=focal_length_px,
                       focal_length_sigma_px=focal_length_sigma_px, disk_readings=disk_readings)
        try:
            with np.errstate(all="ignore"):  # overflow on the way is caught below, not printed
                result = _fit(data, loss, floor, floor_prior_sigma_px, max_irls, pupil, field_curvature)
        except InputError:
            raise
        except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
            return refused_result(data, loss, f"the fit failed numerically ({type(exc).__name__}: {exc}); the samples "
                            "span magnitudes no lens produces: check their units (mm, px) and the pixel pitch")
        try:
            json.dumps(result.to_json_dict(), allow_nan=False)
        except ValueError:
            return refused_result(data, loss, "the fit produced non-finite numbers; the samples span magnitudes no lens "
                            "produces: check their units (mm, px) and the pixel pitch")
        return result

    disk = True if spot_shape == "disk" else ()
    result = run(disk)
    instead = disk_instead(result) if spot_shape == "auto" else None
    if instead:
        disk = set(instead[0])
        result = run(disk)
        result.warnings.append(instead[1])
    if floor_choice and blur_floor_px is None and (sensitive := floor_sensitive(result)):
        widen(result, run(disk, 0.0), sensitive)
    if focusing != "unit" and len(result.samples.labels) > 1:
        options = dict(pixel_pitch_mm=pixel_pitch_mm, loss=loss, blur_floor_px=blur_floor_px,
                       floor_prior_sigma_px=floor_prior_sigma_px, max_irls=max_irls,
                       pupil_magnification=pupil_magnification, field_curvature=field_curvature,
                       spot_shape=spot_shape, floor_choice=floor_choice, focusing="unit", ideal_lens=True)
        result = merge(result, {label: fit(subset(samples, label), focal_length_px=one_setting(focal_length_px, label),
                                           focal_length_sigma_px=one_setting(focal_length_sigma_px, label), **options)
                                for label in result.samples.labels}, focusing)
    nominal.apply(result, ideal_lens, widest_f_number)
    refuse_left_out(result, getattr(samples, "left_out_settings", None) or {})
    return result


def _full_size(c: np.ndarray, free_idx: np.ndarray, m: int) -> np.ndarray:
    """A covariance of the free parameters as one of all parameters (zeros where held)."""
    out = np.zeros((vector_size(m), vector_size(m)))
    out[np.ix_(free_idx, free_idx)] = c
    return out


def refused_result(data: FitData, loss: str, reason: str) -> FitResult:
    """A result that states ``reason`` for every quantity (value None; never NaN)."""
    n, m = len(data.coc_px), len(data.labels)
    none = Estimate(None, reason=reason)
    return FitResult({label: {q: none for q in QUANTITIES} for label in data.labels}, none, Outcome.NOT_IDENTIFIABLE,
                     [reason], [], np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)), math.inf, n, 0, math.nan,
                     math.nan, loss, [], data, np.zeros(n), np.ones(n), np.zeros(vector_size(m)))


@dataclasses.dataclass(frozen=True)
class _Uncertainty:
    """What the uncertainty stage makes: the free parameters' covariance (``cov``) and its full
    size (``full_cov``), condition number and correlations, the variance parts per source, each
    setting's jackknifed calibration term with its degrees of freedom, the strata's degrees of
    freedom (``dof``) and their Student z, the images' shared scatter (``scatter``, ``shared``),
    the blur rows' degrees of freedom and the parameters a near-null direction cannot tell apart."""

    cov: np.ndarray
    cond: float
    corr: np.ndarray
    full_cov: np.ndarray
    parts: dict
    calibration_terms: list
    dof: Any
    z: float
    scatter: Any
    shared: bool
    blur_dof: float
    weak: set


def _uncertainty(solved: stages.Solution, resid: np.ndarray, used: np.ndarray, fnames: list[str]) -> _Uncertainty:
    """The covariance of a solution and its error budget (see the notes inside)."""
    pb, theta, weights, jac, res = solved.problem, solved.theta, solved.weights, solved.jacobian, solved.residuals
    data, m, free_idx, row_on, fpx_w = pb.data, pb.m, pb.free_idx, pb.row_on, pb.fpx_w
    chi2_red, npad = solved.chi2_reduced, padded_size(len(data.coc_px))
    # The blur rows' variance is scaled by their own reduced chi-square, up where they scatter more
    # than their sigmas say and down where less (a Type A evaluation from some hundred degrees of
    # freedom: their stated sigmas carry the estimator's model floor, which on clean stacks is
    # twice their scatter); the calibration's rows and the priors keep their own sigmas.
    # Where the images scatter along the blur's slope beyond what their readings explain (an error
    # of each image's pose: tau > 0), that scatter is a term of its own, shared by each image's
    # edges (images_part, pooled over the images; the images' spread is then not taken), and
    # the readings' chi-square is taken about each image's shared error. Pooled over all the
    # images, it does not rest on the few near the focus plane that set the focus distance.
    named = bool(free_idx.size) and bool(np.all(data.group[used] >= 0))
    cov_fit, cond = svd_covariance(jac, 1.0)  # (J'J)^-1 of the fit as weighted: the images' terms' H^-1
    scatter = image_scatter(theta, m, data, weights * row_on, jac, cov_fit) if named else None
    shared = scatter is not None and scatter.tau > 0  # the images' term is in the budget
    blur_dof = max(float(np.sum(weights[used])) - len(free_idx) - (scatter.images if shared else 0), 1.0)
    chi2_cov = (float(np.sum((weights * row_on * ((resid - scatter.shared) / data.sigma_px) ** 2)[used])) / blur_dof
                if shared else chi2_red)
    jac_w = jac.copy()
    jac_w[:npad] /= math.sqrt(max(chi2_cov, BLUR_SCALE2_MIN))
    cov, _ = svd_covariance(jac_w, 1.0)
    parts_free = budget_parts(jac_w, cov, npad, m)
    # each setting's calibration part whose sigma a jackknife over few views estimated (its views
    # less one degrees of freedom: Welch-Satterthwaite with the rest, effective_z)
    calibration_terms = [(_full_size(cov @ np.outer(jac_w[npad + k], jac_w[npad + k]) @ cov, free_idx, m),
                          float(data.focal_length_dof[k])) for k in range(m)
                         if math.isfinite(data.focal_length_dof[k]) and fpx_w[k] > 0 and free_idx.size]
    images = images_part(jac, cov_fit, data, weights * row_on, scatter)
    if np.any(images):
        parts_free["images"] = images
        cov = cov + images
    arms = arms_part(jac, cov_fit, data, weights * row_on, theta, m)
    if np.any(arms):
        parts_free["spot_shape"] = arms
        cov = cov + arms
    parts = {src: _full_size(c, free_idx, m) for src, c in parts_free.items()}
    strata = None
    if not np.any(np.diag(images) > 0):  # else the images' shared errors are a term of their own
        cov, strata = image_spread(cov, parts_free.get("blur", cov), jac, res, cov_fit, free_idx, data, used)
    dof = (StrataDof([_full_size(c, free_idx, m) for c, _ in strata], [d for _, d in strata])
           if strata else math.inf)
    corr = correlation(cov)
    z = student_z(dof.total if strata else dof)  # for the field curvature and P (each quantity: effective_z)
    full_cov = _full_size(cov, free_idx, m)

    degenerate = cond > MAX_CONDITION
    weak: set[str] = set()
    if degenerate and len(free_idx):
        # The parameters in the near-null direction are the ones that cannot be told apart.
        js = null_direction(jac)
        weak = {fnames[i] for i in range(len(fnames)) if abs(js[i]) > 0.3}

    return _Uncertainty(cov, cond, corr, full_cov, parts, calibration_terms, dof, z, scatter, shared, blur_dof, weak)


def _fit(data: FitData, loss: str, blur_floor_px: float | None, floor_prior_sigma_px: float,
         max_irls: int, pupil: tuple, field_curvature: str = "off") -> FitResult:
    """The body of :func:`fit` on validated data (it may raise on data of absurd magnitude;
    :func:`fit` turns that into a refusal)."""
    labels, m, p = data.labels, len(data.labels), data.pixel_pitch_mm
    t_start = time.perf_counter()
    warnings: list[str] = []
    if data.dropped:
        why = (f" ({data.dropped_truncated} of them: the blur outgrew the clean room around the edge, flag "
               "window_truncated; stop down, or use a target with larger squares, to measure them)"
               if data.dropped_truncated else "")
        warnings.append(f"{data.dropped} sample(s) without a measured blur were left out{why}")
    for label, (share, count) in data.unread_shape.items():
        if share >= UNREAD_SHAPE_WARN:
            warnings.append(f"setting '{label}': its resolved spots are no uniform disks (the disk reads them "
                            f"{100 * share:.0f} % off, a real lens's cores in a halo or bright rims); {count} reading(s) "
                            "whose shape could not be read (spots under 2 px, or edges across depth) carry that share "
                            "of their blur as a model error")

    # ---- what cannot be determined before fitting (per setting)
    blocked = capture_problems(data)
    has_fpx = ~np.isnan(data.focal_length_px)
    no_fpx_reason = ("no focal length in px for this setting (calibration or stack.toml [[intrinsics]]): blur fixes "
                     "only the slope A*s and the focus distance; calibrate on tilted target views to separate f and N")

    # ---- start, free parameters, solve
    fixed_floor = blur_floor_px is not None
    first = stages.start(data, blocked, has_fpx, blur_floor_px, pupil)
    warnings.extend(first.warnings)
    P0, p_source, p_prior, p_note = first.P0, first.p_source, first.p_prior, first.p_note
    at = Layout(m)
    i_p = at.log_p
    pb = stages.problem(data, stages.free_parameters(m, p_source, has_fpx, blocked, fixed_floor),
                        stages.curved_settings(data, blocked, field_curvature), has_fpx, blocked, fixed_floor,
                        floor_prior_sigma_px, p_prior, loss, max_irls)
    solved = stages.solve(pb, first.theta, field_curvature)
    pb, theta, weights, converged = solved.problem, solved.theta, solved.weights, solved.converged
    chi2_red = solved.chi2_reduced
    free, free_idx, curved = pb.free, pb.free_idx, list(pb.curved)
    fpx, fpx_w, floor_w, row_on = pb.fpx, pb.fpx_w, pb.floor_w, pb.row_on
    if not converged:
        warnings.append("Levenberg-Marquardt stopped before its tolerance; estimates may be imprecise")

    pred = predict_all(theta, m, data)
    resid = data.coc_px - pred
    used = row_on > 0
    u = resid / data.sigma_px
    n_used = int(used.sum())
    scale2 = max(1.0, chi2_red)
    n_out = int(np.sum(np.abs(u[used]) > 5 * math.sqrt(scale2)))

    # ---- covariance, condition, correlations
    t_solved = time.perf_counter()
    names = parameter_labels(labels)
    fnames = [names[i] for i in free_idx]
    unc = _uncertainty(solved, resid, used, fnames)
    cov, cond, corr, full_cov, parts, dof, z = unc.cov, unc.cond, unc.corr, unc.full_cov, unc.parts, unc.dof, unc.z
    scatter, shared, blur_dof, weak = unc.scatter, unc.shared, unc.blur_dof, unc.weak
    calibration_terms = unc.calibration_terms

    # ---- a second, distinct V that fits about as well (discrete ambiguity the covariance misses)
    second_vertex(data, theta, full_cov, weights, blocked, fixed_floor, blur_floor_px, scale2)

    # ---- derived quantities
    thin = p_source == "assumed" and theta[i_p] == 0.0
    scale_sigma = data.blur_scale_sigma(weights * row_on)
    settings, reasons, f_est = derive_quantities(theta, full_cov, m, p, data, free, blocked, has_fpx, no_fpx_reason, weak,
                                       dof, thin, parts, scale_sigma**2, blur_dof,
                                       max(scatter.images - 1, 1) if shared else math.inf, calibration_terms)
    for k, label in enumerate(labels):
        settings[label]["field_curvature_per_m"] = curvature_estimate(theta, full_cov, at.curvature(k), k in curved,
                                                                       field_curvature, field_spread(data, k), z)
        warnings.extend(one_sided(label, settings[label]["focus_distance_mm"],
                                   data.w_mean[data.setting == k] * 1000.0, float(theta[at.inv_focus_per_m(k)])))
    if p_source == "assumed":
        p_est = Estimate(P0, 0.0, (P0, P0), (P0, P0),
                         "assumed (a thin lens)" if thin else "assumed (given as pupil_magnification)")
    else:
        sd_p, p_hat = math.sqrt(max(full_cov[i_p, i_p], 0.0)), math.exp(theta[i_p])
        p_est = dataclasses.replace(positive_estimate(p_hat, sd_p, z), reason=p_note)
        if p_source == "prior" and p_note == PHOTOGRAPHIC_P_NOTE:  # the reach f and N were given
            p_est = dataclasses.replace(p_est, ci68=photographic_p_interval(p_hat, sd_p, z[0]),
                                        ci95=photographic_p_interval(p_hat, sd_p, z[1]))
        if parts:
            p_est = dataclasses.replace(p_est, shares=shares_of({src: max(float(c[i_p, i_p]), 0.0)
                                                               for src, c in parts.items()}, sd_p**2))
        if p_source == "fitted" and ("log_P" in weak or sd_p > MAX_RELATIVE_SIGMA):
            p_est = Estimate(None, reason=f"the pupil magnification is poorly constrained (relative 1 sigma "
                             f"{100 * sd_p:.0f}%): focus the settings farther apart")
            reasons.append(f"pupil_magnification: {p_est.reason}")
    code = Outcome.OK if not reasons else Outcome.NOT_IDENTIFIABLE
    return FitResult(settings, f_est, code, reasons, fnames, theta[free_idx], cov, corr, cond, n_used, n_out,
                     chi2_red, float(np.sqrt(np.mean(resid[used] ** 2))) if n_used else 0.0, loss, warnings, data,
                     resid, weights, theta.copy(),
                     dict(free_idx=free_idx, fpx=fpx, fpx_w=fpx_w, floor_w=floor_w, row_on=row_on, p_prior=p_prior),
                     p_est, p_source,
                     stage_seconds={"fit": t_solved - t_start, "uncertainty": time.perf_counter() - t_solved})
