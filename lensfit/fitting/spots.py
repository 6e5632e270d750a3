"""Which blur reading the fit takes where a sample gives two: its spot's second moment read
through the edge estimator's shaped-spot model, or the uniform disk's reading of the same edge.

The second moment is what the fit's model describes for a real lens's aberrated spots (a rim on
one side of focus, a core in a halo on the other), but not for the Airy pattern: its tails fall
off so slowly that its second moment has no finite value, and a reading of it grows with the
window (on exact edges of a disk and an Airy pattern of scale 0.5 px, 4-10 px spots read 2.5-17 %
large through two disks, against 2-7 % through the uniform disk). Where diffraction is modelled (the pipeline's readings through
the Airy pattern) no spot shape is read; where the images were tested and show no Airy pattern
(flag ``airy_not_seen``, ``lensfit.measurement.pipeline``) the shapes are the lens's. Elsewhere (samples
measured without the test, e.g. ``lensfit measure`` then ``lensfit fit samples.csv``, or
``fit(measure(stack))``) the fit looks at the Airy scale its own aperture implies: from
``AUTO_MIN_AIRY_PX`` the pattern is large enough to matter, and the uniform disk's readings are
fitted instead, with a warning that says so.
"""

from __future__ import annotations

import math
from typing import Any

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
