"""What a fit returns: estimates with intervals, the result object, and the results file."""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from lensfit.fitting.constants import EDGE_NODES
from lensfit.fitting.data import FitData
from lensfit.fitting.model import model_np


class Outcome(enum.StrEnum):
    """How a fit ended (a string in files: ``"ok"``, ``"not_identifiable"``)."""

    OK = "ok"
    NOT_IDENTIFIABLE = "not_identifiable"  # some quantity is None; ``FitResult.reasons`` says why


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
    #: the share of the variance each source carries (``lensfit.fitting.uncertainty.BUDGET_SOURCES``;
    #: they sum to 1); None where not computed
    shares: dict[str, float] | None = None

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

    def widened(self, sigma_log: float, source: str, shift_log: float = 0.0) -> "Estimate":
        """A positive quantity times ``exp(shift_log)`` with a term of log-space sigma ``sigma_log``
        (carried by ``source`` in the shares) added to its log-space variance, its intervals'
        log-space multiples of sigma kept."""
        if self.value is None or not self.sigma or sigma_log <= 0:
            return self
        s_log = self.sigma / self.value
        s_new = math.hypot(s_log, sigma_log)
        k = s_new / s_log
        value = self.value * math.exp(shift_log)

        def scaled(ci):
            return None if ci is None else tuple(None if e is None else value * (e / self.value) ** k for e in ci)

        return dataclasses.replace(self, value=value, sigma=value * s_new, ci68=scaled(self.ci68),
                                   ci95=scaled(self.ci95), shares=self.shares_with(source, (sigma_log / s_new) ** 2))

    def shares_with(self, source: str, extra: float) -> dict[str, float] | None:
        """The shares of this estimate's variance once a term from ``source`` makes up ``extra`` of
        the new total (the others scaled down to make room)."""
        if not self.shares:
            return {source: extra} if extra > 0 else None
        return {key: v * (1.0 - extra) for key, v in self.shares.items()} | {source: extra}

    def to_json_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"value": self.value, "sigma": self.sigma,
                               "ci68": list(self.ci68) if self.ci68 else None,
                               "ci95": list(self.ci95) if self.ci95 else None}
        if self.infinite:
            out["infinite"] = True
        if self.reason:
            out["reason"] = self.reason
        if self.shares and self.value is not None:
            out["variance_shares"] = {k: round(float(v), 4) for k, v in self.shares.items()}
        return out


@dataclass
class FitResult:
    """What ``fit`` found.

    Attributes
    ----------
    settings : label -> quantity name (see ``QUANTITIES``) -> :class:`Estimate`
    focal_length_mm : the shared focal length
    code : an :class:`Outcome`: ``"ok"`` or ``"not_identifiable"`` (some quantity is None; see
        ``reasons``)
    reasons : one line per quantity that could not be determined
    parameter_names, parameters, covariance : the free parameters of the solver, their values
        and covariance (``log_f``, ``inv_focus_per_m[k]``, ``log_N[k]``, ``floor_px[k]``)
    correlations : correlation matrix of the free parameters
    condition_number : of the column-equilibrated, weighted Jacobian
    residuals_px, weights : per used sample (measured minus model; final robust weight)
    """

    settings: dict[str, dict[str, Estimate]]
    focal_length_mm: Estimate
    code: Outcome
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
    #: seconds spent solving ("fit") and on the covariance, the images' spread and every reported quantity
    #: ("uncertainty"); kept in memory for ``lensfit bench-stages``, never written
    stage_seconds: dict[str, float] = field(default_factory=dict)
    #: what a developer or camera did to the images (``lensfit.measurement.processing.Processing``), where assessed
    processing: Any = None
    #: which f-number is reported, nominal or the blur's own (``lensfit.fitting.nominal.definition``)
    f_number_definition: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return self.code == Outcome.OK

    def setting_samples(self, label: str) -> int:
        """How many samples of setting ``label`` the fit took (none for a setting left out of the
        measurement: :func:`refuse_left_out`)."""
        labels = self.samples.labels
        return int(np.sum(self.samples.setting == labels.index(label))) if label in labels else 0

    def predict_px(self, setting: str, distance_mm: np.ndarray, pose: bool = False) -> np.ndarray:
        """Model blur diameter (px) of a fronto-parallel edge on the axis at ``distance_mm`` from the lens;
        ``pose``: a distance as the setting's target poses measure it (scaled by its
        calibration's focal length, as the samples' are), not the true one."""
        k = self.samples.labels.index(setting)
        w = 1.0 / np.asarray(distance_mm, np.float64).reshape(-1)
        nodes = np.repeat(w[:, None], EDGE_NODES, axis=1)
        fpx = float(np.nan_to_num(self.samples.focal_length_px[k], nan=0.0))
        return model_np(self._full, len(self.samples.labels), k, nodes, self.samples.pixel_pitch_mm, fpx,
                         float(pose))

    def to_json_dict(self) -> dict[str, Any]:
        """The results file (data_specs/schemas/results.schema.json); finite numbers or null throughout."""
        names = self.parameter_names
        corr = {names[i]: {names[j]: _finite(self.correlations[i, j]) for j in range(len(names))}
                for i in range(len(names))}
        return {
            "focal_length_mm": self.focal_length_mm.to_json_dict(),
            "pupil_magnification": self.pupil_magnification.to_json_dict() | {
                "source": self.pupil_magnification_source},
            "settings": {label: {q: e.to_json_dict() for q, e in qs.items()} | {"samples": self.setting_samples(label)}
                         for label, qs in self.settings.items()},
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
        } | ({"processing": self.processing.to_json_dict()} if self.processing is not None else {}) | (
            {"f_number_definition": self.f_number_definition} if self.f_number_definition is not None else {})


def _finite(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def parameter_labels(labels: list[str]) -> list[str]:
    return (["log_f"] + [f"inv_focus_per_m[{k}]" for k in labels] + [f"log_N[{k}]" for k in labels]
            + [f"floor_px[{k}]" for k in labels] + ["log_P"] + [f"field_curvature_per_m[{k}]" for k in labels])


def results_document(result: FitResult, command: Iterable[str] | None = None,
                     truth: dict[str, Any] | None = None, intrinsics: dict[str, Any] | None = None,
                     image_shape_px: tuple[int, int] | None = None) -> dict[str, Any]:
    """The results JSON with provenance (and, when given, the truth and relative errors, and the
    geometric calibration per setting: ``intrinsics`` maps a label to
    ``lensfit.calibration.camera.Intrinsics``; with ``image_shape_px`` (height, width), each setting's
    angles of view, ``lensfit.optics.view``)."""
    from lensfit.optics.view import field_of_view

    from lensfit.outputs.writers import provenance

    doc = result.to_json_dict()
    doc["provenance"] = provenance("lensfit", list(command) if command else [])
    if not command:
        doc["provenance"]["command"] = None
    if intrinsics:
        doc["calibration"] = {
            label: {"focal_length_px": v.focal_length_px, "focal_length_sigma_px": v.focal_length_sigma_px,
                    "focal_length_sigma_method": v.focal_length_sigma_method,
                    "focal_length_sigma_dof": v.focal_length_sigma_dof, "informative_views": v.informative_views,
                    "principal_point_px": list(v.principal_point_px),
                    "distortion_opencv": [float(x) for x in v.distortion], "rms_px": v.rms_px, "views": v.views,
                    "source": v.source}
            for label, v in intrinsics.items()}
        if image_shape_px and all(image_shape_px):
            for label, v in intrinsics.items():
                doc["calibration"][label]["field_of_view_deg"] = field_of_view(
                    v.focal_length_px, v.focal_length_sigma_px, v.focal_length_sigma_dof, tuple(image_shape_px),
                    tuple(v.principal_point_px))
    if truth is not None:
        doc["truth_comparison"] = compare_with_truth(result, truth)
    return doc


def compare_with_truth(result: FitResult, truth: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows (setting, quantity, estimate, sigma, truth, relative error, within 95 %) for the
    quantities ``truth.json`` states (data_specs/schemas/truth.schema.json)."""
    rows = []
    true_f = truth.get("focal_length_mm")
    per_setting = truth.get("settings") if isinstance(truth.get("settings"), dict) else {}
    for label, qs in result.settings.items():
        t = per_setting.get(label) if isinstance(per_setting.get(label), dict) else {}
        # a lens that breathes (internal focusing) has its own focal length per setting
        for qn, tv in (("focal_length_mm", t.get("focal_length_mm", true_f)), *((q, t.get(q)) for q in (
                "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm", "sensor_distance_mm",
                "aperture_diameter_mm"))):
            if isinstance(tv, bool) or not isinstance(tv, (int, float)) or qn not in qs:
                continue  # (a truth.json written by hand may hold anything: only numbers compare)
            e = qs[qn]
            tv = float(tv)
            rel = None if e.value is None or not math.isfinite(tv) or tv == 0 else e.value / tv - 1
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
    from lensfit.outputs.writers import write_text

    write_text(path, json.dumps(document, indent=1, allow_nan=False))


def refuse_left_out(result: Any, left_out: dict[str, str]) -> None:
    """Each setting the measurement left out (label: why, ``SampleTable.left_out_settings``) into
    ``result`` with every quantity the others report refused, naming why and the fix."""
    if not left_out:
        return
    names = list(dict.fromkeys([q for qs in result.settings.values() for q in qs]
                               + ["focal_length_mm", "f_number", "focus_distance_mm"]))
    for label, why in left_out.items():
        reason = f"setting {label!r} was left out of the measurement: {why}"
        result.settings[label] = {q: Estimate(None, reason=reason) for q in names}
        result.reasons.append(reason)
    result.code = Outcome.NOT_IDENTIFIABLE
