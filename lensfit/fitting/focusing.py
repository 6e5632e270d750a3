"""How the lens focuses, and what that lets settings share.

A lens that focuses **as a unit** (the whole optical block moves; most older and many macro
lenses, and every thin-lens renderer) keeps its focal length f and pupil magnification P at
every focus distance: settings share them, and a focus bracket determines P through
``1/S_k = 1/f - (1/P)(1/X_k)`` (``lensfit.fitting`` notes). Most modern lenses focus
**internally** (one group moves): f and P change with the focus distance ("focus breathing":
a double Gauss focused by its rear group runs 47.4 / 48.4 / 49.0 mm at 0.6 / 1.0 / 1.6 m), and
a shared f is wrong for every setting. The calibration cannot tell the two apart: a unit-focusing
model fitted to the exact per-setting optics of such a lens converges, with residuals below the
calibration's noise, to a P of 2.2 where the true P is about 1.

So the focusing is a property of the lens the user states (``focusing``: ``"unit"``,
``"internal"`` or ``"unknown"``, the default): with ``unit`` the settings are fitted jointly,
sharing f and P; otherwise each setting is fitted by itself (its f and N from its own
calibration, P carried as for one setting), and the joint reading is noted for comparison.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from lensfit.errors import InputError

FOCUSING_MODES = ("unknown", "unit", "internal")
#: The joint (unit-focusing) fit's reduced chi-square over the settings' own fits' at which the
#: note says the data speak against unit focusing: each setting's V is then pulled off its own
#: readings by the shared f and P. Often it cannot tell: on an internally focusing double Gauss
#: (real rays, f/4) the joint fit read 4.0 and the settings apart 5.7, their own misfit from
#: aberrations dominating; hence the default, focusing unknown.
UNIT_MISFIT = 1.5


def check_focusing(value: Any) -> str:
    if value not in FOCUSING_MODES:
        raise InputError("focusing", value, "one of: " + ", ".join(FOCUSING_MODES),
                         "unit where the whole lens moves to focus, internal where a group inside it does")
    return value


def with_lens(samples: Any, pupil_magnification: Any, focusing: str | None, ideal: bool | None = None,
              widest_f_number: float | None = None) -> tuple[Any, Any, str, bool, float | None]:
    """``samples`` (a path read into its SampleTable), and the pupil magnification, focusing,
    whether the lens is ideal and its widest f-number that the fit takes: the arguments, else what
    the samples carry from the stack's ``[lens]``, else none, "unknown", not ideal and none."""
    from pathlib import Path

    from lensfit.io.samples import SampleTable

    if isinstance(samples, (str, Path)):
        samples = SampleTable.read(samples)
    lens = samples.lens if isinstance(samples, SampleTable) else {}
    if pupil_magnification is None:
        pupil_magnification = lens.get("pupil_magnification")
    if ideal is None:
        ideal = lens.get("ideal", False)
    if not isinstance(ideal, bool):
        raise InputError("ideal_lens", ideal, "true or false", "true only for a lens without aberrations (a "
                         "renderer's thin-lens camera)")
    if widest_f_number is None:
        widest_f_number = lens.get("widest_f_number")
    if widest_f_number is not None and not (isinstance(widest_f_number, (int, float)) and not
                                            isinstance(widest_f_number, bool) and 0.5 <= widest_f_number <= 64):
        raise InputError("widest_f_number", widest_f_number, "a number from 0.5 to 64",
                         "the lens's full aperture as its barrel states it (1:1.4 is 1.4), or leave it out")
    return (samples, pupil_magnification, check_focusing(focusing or lens.get("focusing") or "unknown"), ideal,
            None if widest_f_number is None else float(widest_f_number))


def subset(samples: Any, label: str) -> Any:
    """The samples of setting ``label`` alone (a SampleTable keeps its intrinsics for that setting)."""
    from lensfit.fitting.data import samples_from
    from lensfit.io.samples import SampleTable

    if isinstance(samples, SampleTable):
        keep = [i for i, s in enumerate(samples.samples) if str(s.setting) == label]
        return dataclasses.replace(
            samples, samples=[samples.samples[i] for i in keep],
            intrinsics={k: v for k, v in samples.intrinsics.items() if k == label}, left_out_settings={},
            fit_rms=[samples.fit_rms[i] for i in keep] if len(samples.fit_rms) == len(samples.samples) else [],
            edge_tasks=[samples.edge_tasks[i] for i in keep] if len(samples.edge_tasks) == len(samples.samples)
            else [],
            blur_scale=[samples.blur_scale[i] for i in keep] if len(samples.blur_scale) == len(samples.samples)
            else [])
    rows, _ = samples_from(samples)
    return [r for r in rows if r.setting == label]


def one_setting(value: Any, label: str) -> Any:
    """A per-setting argument (a number, or a dict by label) for setting ``label`` alone."""
    if isinstance(value, dict):
        return {label: value[label]} if label in value else None
    return value


def merge(joint: Any, parts: dict[str, Any], focusing: str) -> Any:
    """``joint`` (the unit-focusing fit of every setting, kept for its diagnostics and plots)
    with each setting's quantities, warnings and refusals taken from its own fit, ``parts``;
    the shared focal length and P are replaced by a note that they are per setting."""
    from lensfit.fitting.identifiability import P_NOT_DETERMINED
    from lensfit.fitting.result import Estimate, Outcome

    shared_f, shared_p = joint.focal_length_mm, joint.pupil_magnification
    joint_chi2 = joint.chi2_reduced
    n = sum(part.n_samples for part in parts.values())
    if n:  # the diagnostics of the fits reported, not of the joint one
        joint.chi2_reduced = sum(part.chi2_reduced * part.n_samples for part in parts.values()) / n
        joint.rms_residual_px = math.sqrt(sum(part.rms_residual_px**2 * part.n_samples for part in parts.values()) / n)
        joint.n_outliers = sum(part.n_outliers for part in parts.values())
    why = ("the lens focuses internally" if focusing == "internal" else
           "how the lens focuses is not known (focusing = \"unknown\")")
    joint.focal_length_mm = Estimate(None, reason=f"{why}: f changes with the focus distance, so each setting has its "
                                     "own (settings.<label>.focal_length_mm); declare focusing = \"unit\" where the "
                                     "whole lens moves to focus, to share f and fit P from the bracket")
    joint.pupil_magnification = Estimate(None, reason=f"{why}: P is carried per setting")
    joint.pupil_magnification_source = "prior"
    warnings, reasons = [], []
    for label, part in parts.items():
        joint.settings[label] = part.settings[label]
        warnings += [f"setting {label!r}: {w}" if not w.startswith("setting") else w for w in part.warnings]
        reasons += [r if label in r else f"setting {label!r}: {r}" for r in part.reasons]
    # every setting's P warning says the same: once
    p_notes = [w for w in warnings if P_NOT_DETERMINED in w]
    warnings = [w for w in warnings if w not in p_notes[1:]]
    if shared_f.value is not None:
        fs = ", ".join(f"{label} {part.settings[label]['focal_length_mm'].value:.4g}" for label, part in parts.items()
                       if part.settings[label]["focal_length_mm"].value is not None)
        p_text = (f", P {shared_p.value:.3g} +- {shared_p.sigma:.2g}"
                  if shared_p.value is not None and shared_p.sigma and math.isfinite(shared_p.sigma) else "")
        worse = (f"; together they fit worse (reduced chi-square {joint_chi2:.2g} against {joint.chi2_reduced:.2g} "
                 "apart), so the data speak against unit focusing" if joint_chi2 > UNIT_MISFIT * joint.chi2_reduced
                 else "")
        warnings.append(f"{why}: each setting fitted by itself (f per setting: {fs} mm); were the lens to focus as "
                        f"a unit, the settings together would give f {shared_f.value:.4g} +- {shared_f.sigma:.2g} mm"
                        f"{p_text} (declare focusing = \"unit\" to use that){worse}")
    joint.warnings = warnings
    joint.reasons = reasons
    joint.code = Outcome.OK if not reasons else Outcome.NOT_IDENTIFIABLE
    return joint
