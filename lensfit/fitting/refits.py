"""The fit run again with another choice where the first one's cannot stand, and what is kept.

**Which blur reading** the fit takes where a sample gives two (:func:`disk_instead`): its spot's
second moment read through the edge estimator's shaped-spot model, or the uniform disk's reading
of the same edge.

The second moment is what the fit's model describes for a real lens's aberrated spots (a rim on
one side of focus, a core in a halo on the other), but not for the Airy pattern: its tails fall
off so slowly that its second moment has no finite value, and a reading of it grows with the
window (on exact edges of a disk and an Airy pattern of scale 0.5 px, 4-10 px spots read 2.5-17 %
large through two disks, against 2-7 % through the uniform disk). Where diffraction is modelled
(the pipeline's readings through the Airy pattern) no spot shape is read; where the images were
tested and show no Airy pattern (flag ``airy_not_seen``, ``lensfit.measurement.pipeline``) the
shapes are the lens's. Elsewhere (samples measured without the test, e.g. ``lensfit measure``
then ``lensfit fit samples.csv``, or ``fit(measure(stack))``) the fit looks at the Airy scale
its own aperture implies: from ``AUTO_MIN_AIRY_PX`` the pattern is large enough to matter, and
the uniform disk's readings are fitted instead, with a warning that says so.

**A one-sided setting's blur floor**: its intervals widened to span the fit without the floor
(:func:`widen`).

Where every sample of a setting lies on one side of its focus distance, the V's vertex is
extrapolated from one arm, and a blur floor (added in quadrature) and a shift of the focus
distance bend that arm's small-blur end alike: the data cannot tell them apart. The fit's
covariance does not carry this. Where it fits a floor the model takes ``b^2`` (so a floor at 0
moves nothing to first order), and where it fits one above 0 the floor is pinned by whichever
readings happen to be smallest. An end-to-end fuzz of random scenes (28 answered
one-sided stacks, 52 one-sided intervals of N and the focus distance) saw both. A 13 mm f/4
stack diffracting at 0.6 px had a floor of 0.81 px, N -4.5 % at 3.9 sigma and the focus
distance -8.7 % at 7.6 sigma; fitted without the floor, +0.4 % each. On a 27 mm f/2.4 bracket
one board at the plane in focus read 0.7 px for 0.29 px, which a floor of 0.68 px took up: N
-1.2 % and the focus distance -1.1 % at 4 and 6 sigma; without the floor, +1.2 % and +0.5 %.
Elsewhere the floor was right and the fit without it wrong (two stacks at 4-7 sigma). Neither
fit is the better one on such data, so the reported intervals span both (:func:`widen`): each
quantity of the setting takes the difference ``d`` between the two fits as a term of its own,
``sigma^2 + d^2`` (variance source ``floor_choice``). Measured on those 52 intervals: 47 held the
truth as fitted, 48 without the floor, 51 with the term; the intervals widened 1.0-1.7x on most
settings, 2-3x on two and 4-9x on the two stacks above.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from lensfit.fitting.constants import FLOOR_SADDLE_PX
from lensfit.fitting.model import Layout
from lensfit.fitting.result import Estimate, Outcome
from lensfit.fitting.start import one_side
from lensfit.fitting.uncertainty import focus_interval
from lensfit.measurement.diffraction import DEFAULT_WAVELENGTH_NM, MAX_AIRY_PX, airy_scale_px, working_f_number

#: How the fit takes readings that come in two (``fit(spot_shape=...)``).
SPOT_SHAPE_MODES = ("auto", "shaped", "disk")
#: The Airy scale (px, at 550 nm) from which untested samples' second moments are set aside for the
#: uniform disk's readings (and down to which the pipeline's diffraction test tries fractions of
#: the first fit's scale). Below it the tails still add an offset to every reading (0.1 px at a =
#: 0.16 px), which a fit with every target on one side of the focus takes for its focus distance:
#: the pipeline tests the images from lensfit.measurement.pipeline.TEST_MIN_AIRY_PX.
AUTO_MIN_AIRY_PX = 0.5


def airy_per_setting(result: Any, wavelength_nm: float = DEFAULT_WAVELENGTH_NM) -> dict[str, float]:
    """Each setting's Airy scale ``lambda N_w / p`` (px) from a fit: ``N_w = f_px p / A``. Where
    the fit reported no aperture (the Airy pattern itself can make the f-number too uncertain to
    report before diffraction is modelled) its solution's ``A = f / N`` serves; a setting without
    one, or whose scale is beyond ``MAX_AIRY_PX`` (what the edge estimator's model reads: where
    every blur sits below a pixel the solution's f-number can run off to 1e10, which had stopped
    the auto diffraction test with an internal error), takes the median scale of the others (0 if
    none)."""
    from lensfit.fitting.model import Layout

    data = result.samples
    pitch = data.pixel_pitch_mm
    at = Layout(len(data.labels))
    out: dict[str, float] = {}
    for k, label in enumerate(data.labels):
        quantities = result.settings[label]
        # The real cone's aperture where the nominal one is reported (lensfit.fitting.nominal).
        a = quantities.get("aperture_diameter_effective_mm", quantities["aperture_diameter_mm"]).value
        if a is None and len(result._full) == at.size:
            a = math.exp(result._full[at.LOG_F] - result._full[at.log_n(k)])
        fpx = float(data.focal_length_px[k])
        if math.isfinite(fpx) and a and math.isfinite(a) and a > 0:
            scale = airy_scale_px(wavelength_nm, working_f_number(fpx * pitch, a), pitch)
            if 0.0 < scale <= MAX_AIRY_PX:
                out[label] = scale
    known = sorted(out.values())
    fill = known[len(known) // 2] if known else 0.0
    return {label: out.get(label, fill) for label in data.labels}


def disk_instead(result: Any) -> tuple[list[str], str] | None:
    """The settings whose samples the fit ``result`` (of shaped readings, ``spot_shape`` "auto")
    should take at the uniform disk's readings, and why; None where it stands."""
    data = result.samples
    if not data.shaped.any() or data.airy_checked or not any(result._full):  # (a refused fit has no solution)
        return None
    shaped = {data.labels[k] for k in set(data.setting[data.shaped].tolist())}
    large = {k: v for k, v in airy_per_setting(result).items() if v >= AUTO_MIN_AIRY_PX and k in shaped}
    if not large:
        return None
    scales = ", ".join(f"{k} {v:.2f} px" for k, v in large.items())
    return list(large), (
        f"the spots' shapes were not used on setting(s) {', '.join(map(repr, large))}: at the fitted aperture the "
        f"Airy pattern at 550 nm has a scale of {scales}, whose tails a second moment counts as blur, and these "
        "samples were not tested for it; the uniform disk's readings were fitted there instead (`lensfit fit STACK` "
        "tests the images, models the pattern where they show it and reads the shapes where they do not)")


#: The setting's quantities the choice moves (the focal length is shared by every setting and
#: moved by under 0.01 % on the fuzz's stacks; the focus distances follow their inverse).
_LOG_SCALE = ("f_number", "aperture_diameter_mm", "sensor_distance_mm", "blur_slope_mm2")


def floor_sensitive(result: Any) -> list[str]:
    """The settings of ``result`` whose samples all lie on one side of a reported, finite focus
    distance and whose fitted blur floor is above 0: where a fit without the floor
    (``blur_floor_px=0``) can move the focus distance and the f-number."""
    if not len(result._full) or result.samples is None:
        return []
    data, at = result.samples, Layout(len(result.samples.labels))
    out = []
    for k, label in enumerate(data.labels):
        qs = result.settings.get(label, {})
        focus, floor = qs.get("focus_distance_mm"), qs.get("blur_floor_px")
        if (focus is None or focus.value is None or focus.ci95 is None or focus.ci95[1] is None
                or floor is None or floor.value is None or floor.value <= FLOOR_SADDLE_PX):
            continue
        w = data.w_mean[data.setting == k] * 1000.0
        if w.size and one_side(w, float(result._full[at.inv_focus_per_m(k)])) is not None:
            out.append(label)
    return out


def widen(result: Any, without_floor: Any, labels: list[str]) -> None:
    """Widen, in place, the intervals of ``result``'s settings ``labels`` to span the fit
    ``without_floor`` (the same data, floor held at 0): each quantity's variance gains the square
    of the two fits' difference, its intervals the same multiples of the new sigma, and a warning
    says what the fit without the floor read."""
    for label in labels:
        mine, other = result.settings[label], without_floor.settings.get(label, {})
        inv, inv_alt = mine.get("inverse_focus_distance_per_m"), other.get("inverse_focus_distance_per_m")
        if inv is None or inv.value is None or not inv.sigma:
            continue
        if inv_alt is None or inv_alt.value is None:
            _refuse(result, label, other)
            continue
        new_inv = _linear(inv, inv_alt.value)
        mine["inverse_focus_distance_per_m"] = new_inv
        focus = mine["focus_distance_mm"]
        if focus.value is not None and new_inv.value > 0:
            mine["focus_distance_mm"] = _distance(focus, new_inv, 0.0)
            sensor = mine.get("focus_distance_from_sensor_mm")
            if sensor is not None and sensor.value is not None:
                mine["focus_distance_from_sensor_mm"] = _distance(sensor, new_inv, sensor.value - focus.value)
        for name in _LOG_SCALE:
            est, alt = mine.get(name), other.get(name)
            if est is not None and alt is not None and est.value and alt.value and est.sigma:
                mine[name] = _log(est, alt.value)
        floor = mine.get("blur_floor_px")
        if floor is not None and floor.value is not None and floor.sigma:
            mine["blur_floor_px"] = _linear(floor, 0.0, lower=0.0)
        alt_focus, alt_n = other.get("focus_distance_mm"), other.get("f_number")
        said = ", ".join(part for part in (
            f"focus distance {alt_focus.value:.4g} mm" if alt_focus is not None and alt_focus.value else "",
            f"f-number {alt_n.value:.4g}" if alt_n is not None and alt_n.value else "") if part)
        result.warnings.append(
            f"setting {label!r}: with every sample on one side of the focus, the fitted blur floor "
            f"({floor.value:.2f} px) cannot be told from a shift of the focus distance; fitted without a floor it "
            f"reads {said or 'otherwise'}, and the intervals span both (variance source floor_choice)")


def _refuse(result: Any, label: str, other: dict[str, Estimate]) -> None:
    """Setting ``label``'s quantities that the fit without the floor could not determine (``other``
    its settings), refused: on one side of the focus, only the fitted floor locates them."""
    floor = result.settings[label]["blur_floor_px"].value
    refused = []
    for name, est in list(result.settings[label].items()):
        alt = other.get(name)
        if name in ("focal_length_mm", "blur_floor_px", "field_curvature_per_m") or est.value is None or (
                alt is not None and alt.value is not None):
            continue
        why = (f"with every sample of setting {label!r} on one side of its focus distance, only the fitted blur floor "
               f"({floor:.2f} px) locates it: fitted without a floor, "
               f"{(alt.reason if alt is not None else None) or 'it is not determined'}")
        result.settings[label][name] = Estimate(None, reason=why)
        refused.append(name)
    if refused:
        result.reasons.append(f"settings.{label} ({', '.join(refused)}): {why}")
        result.code = Outcome.NOT_IDENTIFIABLE


def _linear(est: Estimate, alt: float, lower: float | None = None) -> Estimate:
    """``est`` with ``(alt - value)^2`` added to its variance, intervals scaled about the value."""
    d = alt - est.value
    sigma = math.hypot(est.sigma, d)
    k = sigma / est.sigma

    def scaled(ci):
        if ci is None:
            return None
        lo, hi = (None if e is None else est.value + (e - est.value) * k for e in ci)
        return (max(lo, lower) if lo is not None and lower is not None else lo, hi)

    return dataclasses.replace(est, sigma=sigma, ci68=scaled(est.ci68), ci95=scaled(est.ci95),
                               shares=est.shares_with("floor_choice", (d / sigma) ** 2 if sigma > 0 else 0.0))


def _log(est: Estimate, alt: float) -> Estimate:
    """A positive quantity: the log-space difference added to its log-space variance, its
    intervals' log-space multiples kept."""
    return est.widened(abs(math.log(alt / est.value)), "floor_choice")


def _distance(est: Estimate, inv: Estimate, offset_mm: float) -> Estimate:
    """A focus distance (plus ``offset_mm``: from the sensor) from its widened inverse ``inv``
    (per m): sigma by the delta method, intervals the inverse's mapped (None: infinity)."""
    def dist(ci):
        return None if ci is None else tuple(None if e is None else e + offset_mm for e in focus_interval(*ci))

    value = 1000.0 / inv.value
    return dataclasses.replace(est, sigma=value * inv.sigma / inv.value, ci68=dist(inv.ci68), ci95=dist(inv.ci95),
                               shares=inv.shares)
