"""From a stack to a fit, with diffraction modelled where asked: measure, fit, and where the
lens is stopped down far enough to be diffraction-limited, measure again with each setting's
Airy pattern in the edge model and fit again, until the f-number settles.

The Airy pattern's scale depends on the working f-number ``N_w = S / A`` (``S = f_px p`` the
calibration's pinhole distance, ``A`` the fitted entrance-pupil diameter), which the first fit
gives with the diffraction still in the blur (several per cent off at ``a`` of 1-2 px); each
round takes ``A`` from the last fit. Two to four rounds settle it within 0.1 %.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

from lensfit.diffraction import DEFAULT_WAVELENGTH_NM, airy_scale_px, working_f_number
from lensfit.errors import InputError

#: Re-measurements at most, and the change of every f-number below which they stop.
MAX_ROUNDS = 4
SETTLED_REL = 1e-3


def airy_per_setting(table: Any, result: Any, wavelength_nm: float) -> dict[str, float]:
    """Each setting's Airy scale ``lambda N_w / p`` (px) from a fit: ``N_w = f_px p / A``. Where
    the fit reported no aperture (the Airy pattern itself can make the f-number too uncertain to
    report before diffraction is modelled) its solution's ``A = f / N`` serves as the start; a
    setting without one takes the median scale of the others (0 if none)."""
    from lensfit.fit.model import Layout

    pitch = table.pixel_pitch_mm
    at = Layout(len(result.samples.labels))
    out: dict[str, float] = {}
    for label, qs in result.settings.items():
        intr = table.intrinsics.get(label)
        a = qs["aperture_diameter_mm"].value
        if a is None and len(result._full) == at.size:
            k = result.samples.labels.index(label)
            a = math.exp(result._full[at.LOG_F] - result._full[at.log_n(k)])
        if intr is not None and a and math.isfinite(a) and a > 0:
            out[label] = airy_scale_px(wavelength_nm, working_f_number(intr.focal_length_px * pitch, a), pitch)
    known = sorted(out.values())
    fill = known[len(known) // 2] if known else 0.0
    return {label: out.get(label, fill) for label in result.settings}


def measure_and_fit(stack: Any, estimator: str = "edge", *, wavelength_nm: float | None = None,
                    fit_options: dict[str, Any] | None = None,
                    progress: Callable[[str, int, int], None] | None = None) -> tuple[Any, Any, list[dict[str, float]]]:
    """Measure ``stack`` and fit it; with ``wavelength_nm`` (the light's effective wavelength, e.g.
    550 for a grey or green-weighted image) model diffraction in the blur readings.

    Returns (samples, fit result, rounds): ``rounds`` lists the Airy scales (px per setting) each
    diffraction round measured with (empty without diffraction).

    Raises
    ------
    InputError
        A wavelength outside 200-2000 nm, or an estimator without a diffraction model.
    """
    from lensfit.fit import fit
    from lensfit.measure import measure
    from lensfit.stack import Stack, load_stack

    if wavelength_nm is not None and not (math.isfinite(wavelength_nm) and 200.0 <= wavelength_nm <= 2000.0):
        raise InputError("wavelength_nm", wavelength_nm, "between 200 and 2000 nm",
                         f"the effective wavelength of the light, e.g. {DEFAULT_WAVELENGTH_NM:g}")
    if wavelength_nm is not None and estimator not in ("edge", "edge-disk"):
        raise InputError("estimator", estimator, "edge or edge-disk where diffraction is modelled")
    if not isinstance(stack, Stack):
        stack = load_stack(Path(stack))
    options = dict(fit_options or {})
    table = measure(stack, estimator, progress=progress)
    result = fit(table, **options)
    rounds: list[dict[str, float]] = []
    if wavelength_nm is None:
        return table, result, rounds
    for _ in range(MAX_ROUNDS):
        airy = airy_per_setting(table, result, wavelength_nm)
        if not any(airy.values()):
            result.warnings.append("diffraction not modelled: no setting's aperture was determined")
            break
        rounds.append(airy)
        new_table = measure(stack, estimator, progress=progress, airy_px=airy)
        new = fit(new_table, **options)
        change = max((abs(new.settings[k]["f_number"].value / result.settings[k]["f_number"].value - 1.0)
                      for k in new.settings if new.settings[k]["f_number"].value
                      and result.settings.get(k, {}).get("f_number") and result.settings[k]["f_number"].value),
                     default=0.0)
        table, result = new_table, new
        if change < SETTLED_REL:
            break
    return table, result, rounds
