"""What a raw developer or a camera's JPEG engine did to a stack's images, as far as lensfit can
tell, and what it does to the f-number.

Blur is read from edge profiles in linear light. A developed image (a camera's JPEG, a raw
developer's export) went through a tone curve beyond the sRGB encoding it declares and through
sharpening: the tone curve narrows every edge by some percent, sharpening takes about half a
pixel off each, and the fitted blur floor cannot go below zero, so the f-number absorbs both and
reads high (5-20 % with common defaults) while its interval stays narrow. Neither the focal
length nor the focus distance depends on the blur's scale, and they stay right.

Two kinds of evidence, each enough:

- the files' EXIF: a ``Software`` tag naming a raw developer, or a JPEG written by a camera
  (its ``Make``, and the firmware as ``Software``);
- halos on the edges (``lensfit.estimators.halo``): an overshoot no lens makes, the mark of
  sharpening, wherever the file came from.

Images declared sRGB-encoded (``encoding = "srgb"``, the default for JPEG) with either evidence
have their f-number (and the aperture diameter) refused by default, naming the processing and
the fix: the RAW files, or a linear export without sharpening. Images declared linear are read
as they are (a linear TIFF from a developer is the advice), their EXIF and halos unchecked.

A third test holds for every stack, whatever its declared encoding: the tone response. Blur is
read from edges as the declared encoding decodes them; where the files hold another tone curve
(a developer's, a film look, an sRGB file declared linear), every edge is warped alike and its
midpoint moves toward one side. The target's corners (saddle points, which a monotone tone curve
leaves in place) say where the edges lie; in linear light a lens draws each edge on the line
through them, up to its spot's asymmetry, which cancels between the two sides of a checkerboard's
edges (as many dark-to-bright as bright-to-dark along each line). The edges' pooled offset toward
their bright side, in blur radii (:data:`TONE_MIN_OFFSET`), names the mismatch. Measured on the
demo stack re-encoded with gamma curves and declared linear: 1.1 -> -0.033 of a radius (N
-0.8 %, its interval excluding the truth), 1.25 -> -0.074 (N -1.7 %), 1.5 -> -0.126 (N
-2.3 %); darktable's default export (filmic, +0.7 EV) -0.097 (N +6 %); the linear renders and
the real-ray stacks of four published designs 0.000 to -0.010.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: ``Software`` tags of raw developers and photo editors (case-insensitive, anywhere in the tag).
DEVELOPERS = re.compile(r"darktable|rawtherapee|\bART\b|lightroom|camera raw|photoshop|capture one|dxo|\bon1\b|"
                        r"luminar|affinity|gimp|digikam|silkypix|acdsee|pixelmator|aperture|snapseed|exposure x|"
                        r"lightzone|filmulator|photolab|capture nx|nx studio|digital photo professional|"
                        r"imaging edge|olympus workspace|om workspace|raw power|photos \d|iphoto|polarr|"
                        r"photoscape|rawdigger|dcraw|libraw", re.IGNORECASE)
#: Writers whose JPEGs hold the sRGB encoding alone (no tone curve, no sharpening): lensfit's own
#: renderer names itself so.
FAITHFUL = re.compile(r"^lensfit\b", re.IGNORECASE)
#: Halos: the pooled unsharp-mask amount (``lensfit.estimators.halo``) above this, and this many
#: standard errors from 0. An image as the lens drew it reads about 0 (the shipped demo 0.0000 +-
#: 0.0008) or below 0 (strong spherical aberration, a core in a halo: -1.3); an in-camera
#: pipeline's 1 px mask +0.17 +- 0.016.
HALO_MIN_AMOUNT = 0.05
HALO_MIN_Z = 5.0
#: What to do where processing biases the blur readings: fit it (``model``: the tone curve and
#: sharpening read from the edges, ``lensfit.estimators.tone``; N refused where they do not hold
#: the images), refuse N outright, or report it with a warning.
POLICIES = ("model", "refuse", "report")
#: The tone curves' sine terms the processing is fitted with: the first gives the readings, the
#: second's N differs by what the curve's form leaves open, which the interval carries.
MODEL_TERMS = (4, 6)
#: The processing model holds a stack's images where the two curves' f-numbers agree within
#: ``MODEL_MAX_SPREAD`` (what the curve's form leaves open) and it misses the profiles by no more
#: than their noise can explain: a misfit both significant (joint reduced chi-square above
#: ``MODEL_MAX_CHI2``) and material (RMS beyond the noise above ``MODEL_MAX_MISFIT`` of the edges'
#: contrast) is processing of another kind, whose blur readings the model does not vouch for.
#: (Either alone misjudges: a reduced chi-square grows with the signal to noise for one same small
#: misfit, and noisy images hide a material one.) Measured, chi-square / misfit: where the model
#: is the processing (DNGs developed by darktable's defaults, a camera-like S curve with a 1 px
#: unsharp mask and 4:2:0 JPEG) 1.3-1.7 / 0.003-0.008, blurs within 1.5 %; RawTherapee's capture
#: sharpening (a deconvolution in linear light) 2.9 / 0.0067, blurs 4-18 % small; noise
#: reduction besides a mask 5.6 / 0.014.
MODEL_MAX_CHI2 = 2.5
MODEL_MAX_MISFIT = 0.005
MODEL_MAX_SPREAD = 0.04
#: The error of the model's form, relative, 1 sigma, carried into every f-number read through it:
#: the processing is never exactly a warp of sRGB and one unsharp mask, and its fitted parameters'
#: covariance does not see what the form leaves out. Measured on the camera-raw scene's DNGs
#: through eight pipelines the model holds (darktable's default, with and without its Software
#: tag; S curves over LibRaw's encoding with unsharp masks from 0.6 px x 1.5 to 1.5 px x 0.5; a
#: 3 x 3 median before the mask; the encoding alone): N off by -1.4 to +1.7 % (RMS 0.8 %), where
#: the covariance said 0.2-0.4 %.
MODEL_FORM_SIGMA = 0.009
#: The Airy scale (lambda N / pixel pitch at 550 nm, px) from which the model holds the Airy
#: pattern: below it the pattern is narrower than the pixel integration that every edge carries.
MODEL_AIRY_PX = 0.25
#: A reading through the model less certain than this (px) is no reading.
MAX_SIGMA_PX = 1e3
#: A reduced chi-square above this is flagged with its likely causes (renders through a thin lens
#: and real-ray renders of stopped-down lenses read about 1-3; an in-camera JPEG pipeline 8.9).
MISFIT_CHI2 = 3.0
#: The tone test: the edges' pooled offset toward their bright side, in blur radii, above this
#: (about 0.7 % of N for a gamma mismatch, three times the largest offset of a linear stack
#: measured: -0.010, a retrofocus's real rays), by this many standard errors, over at least this
#: many edges of at least ``TONE_MIN_DIAMETER_PX`` (smaller ones are mostly pixel).
TONE_MIN_OFFSET = 0.03
TONE_MIN_Z = 5.0
TONE_MIN_EDGES = 20
TONE_MIN_DIAMETER_PX = 2.0


@dataclass
class Processing:
    """What is known of the processing of a stack's images.

    Attributes
    ----------
    developer : what the EXIF names (a raw developer, or a camera's JPEG engine), or None
    developed_files : the images the EXIF says were developed
    encoded : whether any image is declared sRGB-encoded (not linear)
    tone_offset, tone_sigma, tone_edges : the edges' pooled offset toward their bright side from
        the lines through the target's corners, in blur radii, its standard error and the edges
        it rests on (NaN, 0 where not tested)
    halo_amount, halo_sigma, halo_edges : the pooled unsharp-mask amount, its standard error and
        the edges it rests on (NaN, 0 where not tested)
    """

    developer: str | None = None
    developed_files: list[str] = field(default_factory=list)
    encoded: bool = False
    halo_amount: float = math.nan
    halo_sigma: float = math.nan
    halo_edges: int = 0
    tone_offset: float = math.nan
    tone_sigma: float = math.nan
    tone_edges: int = 0
    #: the processing model fitted to the edges (``read_through``), a summary for the results
    #: file; None where it was not fitted
    model: dict[str, Any] | None = None
    #: whether the f-number was read through that model (which then holds the images)
    modelled: bool = False

    @property
    def halos(self) -> bool:
        """Sharpening halos on the edges (see ``HALO_MIN_AMOUNT``, ``HALO_MIN_Z``)."""
        return (math.isfinite(self.halo_amount) and self.halo_amount > HALO_MIN_AMOUNT
                and self.halo_amount > HALO_MIN_Z * self.halo_sigma)

    @property
    def tone_mismatch(self) -> bool:
        """A tone response the declared encoding does not undo (see the module notes)."""
        return offset_significant(self.tone_offset, self.tone_sigma, self.tone_edges)

    @property
    def biases_f_number(self) -> bool:
        """Whether the blur readings, so the f-number, are biased by processing lensfit does not model."""
        return not self.modelled and self.processed

    @property
    def processed(self) -> bool:
        """Whether the evidence says the images went through processing the plain blur readings do
        not model (whether or not the processing model then read them)."""
        return (self.encoded and (self.developer is not None or self.halos)) or self.tone_mismatch

    def describe(self) -> str:
        """What was found, in one clause."""
        parts = []
        if self.developer:
            parts.append(f"the images were developed ({self.developer}: a tone curve beyond sRGB, often sharpening)")
        if self.halos:
            parts.append(f"their edges show sharpening halos (unsharp-mask amount {self.halo_amount:.2f} +- "
                         f"{self.halo_sigma:.2f} over {self.halo_edges} edges; a lens makes none)")
        if self.tone_mismatch:
            side = "dark" if self.tone_offset < 0 else "bright"
            parts.append(f"the edges lie {abs(self.tone_offset):.3f} +- {self.tone_sigma:.3f} of a blur radius "
                         f"toward their {side} side of the target corners' lines over {self.tone_edges} edges: a "
                         f"tone curve the declared encoding ({'srgb' if self.encoded else 'linear'}) does not undo "
                         "(a lens draws them on the lines in linear light)")
        return " and ".join(parts)

    def reason(self) -> str:
        """The f-number's refusal: the cause and the fix."""
        why = (self.model or {}).get("why")
        model = f"; a tone curve and sharpening fitted to the edges do not hold these images ({why})" if why else ""
        if not (self.encoded and (self.developer is not None or self.halos)):  # the tone test alone
            return (f"{self.describe()}{model}; a tone curve warps every edge, which moves N by percents with an "
                    "interval that does not hold it: declare the encoding the files hold (encoding = \"srgb\" for "
                    "sRGB files, \"linear\" for linear ones) or fit the RAW files; the focal length and focus "
                    "distance do not depend on it and are reported")
        return (f"{self.describe()}{model}; a developer's tone curve and sharpening narrow every edge, which reads N "
                "5-20 % high with an interval that does not hold it: fit the RAW files (lensfit init takes RAW "
                "where a camera wrote RAW + JPEG), or export linear TIFF without sharpening or noise reduction and "
                "declare it encoding = \"linear\"; the focal length and focus distance do not depend on it and are "
                "reported")

    def to_json_dict(self) -> dict[str, Any]:
        """The results file's ``processing`` object."""
        return {"developer": self.developer, "developed_files": list(self.developed_files),
                "encoded": self.encoded, "halos": self.halos,
                "halo_amount": _finite(self.halo_amount), "halo_sigma": _finite(self.halo_sigma),
                "halo_edges": self.halo_edges, "tone_offset": _finite(self.tone_offset),
                "tone_sigma": _finite(self.tone_sigma), "tone_edges": self.tone_edges,
                "tone_mismatch": self.tone_mismatch, "f_number_biased": self.biases_f_number,
                "model": _finite(self.model), "f_number_modelled": self.modelled}


def _finite(value: Any) -> Any:
    """``value`` with every non-finite number (which JSON cannot hold) made None, inside lists and dicts."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def developer_of(path: Path, record: Any) -> str | None:
    """What developed the image at ``path`` by its EXIF (``record``, a ``lensfit.io.exif.CameraRecord``):
    a raw developer's ``Software`` tag, or a camera that wrote a JPEG; None (RAW and DNG files,
    files without such tags, lensfit's own renders)."""
    from lensfit.io.images import JPEG_SUFFIXES, RAW_SUFFIXES

    suffix = path.suffix.lower()
    software, maker = record.software or "", record.make or ""
    if suffix in RAW_SUFFIXES:
        return None
    # a developer's name first: its output keeps the camera's Make, lensfit's own renders' too
    if DEVELOPERS.search(software):
        return software
    if FAITHFUL.search(software) or FAITHFUL.search(maker):
        return None
    if suffix in JPEG_SUFFIXES and maker:
        return "in-camera JPEG of the " + (record.camera or maker) + (f", {software}" if software else "")
    return None


def from_exif(stack: Any) -> Processing:
    """The EXIF evidence of a stack's sRGB-encoded images (images declared linear are read as
    they are, and their EXIF is not consulted)."""
    from lensfit.io.exif import read_camera_record

    found = Processing(encoded=stack.encoded)
    for im in stack.images:
        if im.encoding != "srgb":  # (linear images keep today's path, untouched)
            continue
        name = developer_of(im.file, read_camera_record(im.file))
        if name:
            found.developed_files.append(im.file.name)
            found.developer = found.developer or name
    return found


def assess(stack: Any, profiles: dict[str, Any] | None, table: Any = None) -> Processing:
    """The EXIF, halo and tone evidence of a measured stack (``profiles``: the edge profiles its
    ``lensfit.measurement.measure.Measurement`` kept, ``keep_profiles=True``; without them the
    halos are not tested; ``table``: its samples, whose edges' offsets the tone test pools)."""
    import numpy as np

    from lensfit.estimators.halo import halo_amounts, pooled

    found = from_exif(stack)
    state = (profiles or {}).get("state")
    if state is not None and found.encoded:
        radius, batch, index = state[1], state[7], state[8]
        amounts, var = halo_amounts(batch, [radius[i] for i in index])
        found.halo_amount, found.halo_sigma, found.halo_edges = pooled(np.asarray(amounts), np.asarray(var))
    if table is not None:
        found.tone_offset, found.tone_sigma, found.tone_edges = tone_offset(table)
    return found


def tone_offset(table: Any) -> tuple[float, float, int]:
    """The edges' mean offset toward their bright side from the lines through the target's
    corners, in blur radii (each edge's offset over half its blur diameter), its standard error
    and the number of edges (module notes; NaN, NaN, 0 with fewer than two)."""
    return pooled_offset(zip(table.bright_offset_px, (s.coc_diameter_px for s in table.samples)))


def pooled_offset(readings: Any) -> tuple[float, float, int]:
    """:func:`tone_offset` of ``(offset px, blur diameter px)`` pairs (either None where not read)."""
    import numpy as np

    values = [off / (0.5 * d) for off, d in readings
              if off is not None and d is not None and d >= TONE_MIN_DIAMETER_PX and math.isfinite(off)]
    if len(values) < 2:
        return math.nan, math.nan, len(values)
    v = np.asarray(values)
    return float(v.mean()), float(v.std(ddof=1) / math.sqrt(len(v))), len(v)


def offset_significant(offset: float, sigma: float, edges: int) -> bool:
    """Whether a pooled offset (:func:`pooled_offset`) names a tone mismatch (``TONE_MIN_*``)."""
    return (edges >= TONE_MIN_EDGES and math.isfinite(offset) and abs(offset) > TONE_MIN_OFFSET
            and abs(offset) > TONE_MIN_Z * sigma)


def apply(result: Any, found: Processing, policy: str = "refuse") -> None:
    """Say in ``result`` (a ``FitResult``) what ``found`` says: its ``processing``, a warning, and
    under ``policy = "refuse"`` every setting's f-number and aperture diameter refused with the
    cause and the fix."""
    from lensfit.fitting.result import Estimate, Outcome

    result.processing = found
    if math.isfinite(result.chi2_reduced) and result.chi2_reduced > MISFIT_CHI2:
        cause = (found.describe() if found.biases_f_number else
                 "likely causes: images developed or sharpened beyond what their EXIF and edges show, a lens's "
                 "aberrations wide open (stop down), or a lens that moved between shots")
        result.warnings.append(f"the blur readings scatter about the fitted V {math.sqrt(result.chi2_reduced):.1f} "
                               f"times more than their noise (reduced chi-square {result.chi2_reduced:.1f}); the "
                               f"intervals are widened by it, but a systematic cause is not noise: {cause}")
    if not found.biases_f_number:  # (halos are looked for on sRGB-encoded images only, so they bias it)
        return
    if policy == "report":
        result.warnings.append(f"{found.describe()}: the f-number is off by percents (a developer's processing "
                               "reads it 5-20 % high) and its interval does not carry it (--processed report); fit "
                               "the RAW files for a trustworthy N")
        return
    reason = found.reason()
    for quantities in result.settings.values():
        for q in ("f_number", "f_number_effective", "aperture_diameter_mm", "aperture_diameter_effective_mm"):
            before = quantities.get(q)
            if before is not None:  # (a reason of its own is kept after the processing's)
                quantities[q] = Estimate(None, reason=reason if before.value is not None or not before.reason
                                         else f"{reason}; besides, {before.reason}")
    result.reasons.append(f"f_number: {reason}")
    result.code = Outcome.NOT_IDENTIFIABLE


def read_through(measurement: Any, table: Any, found: Processing, options: dict[str, Any],
                 airy_px: dict[str, float] | None = None) -> tuple[Any, Any] | None:
    """The stack's edges read through the processing fitted to them (``lensfit.estimators.tone``)
    and fitted again: ``(samples, fit result)`` where the model holds the images, with the
    f-number's interval carrying the model's uncertainty (the shared parameters' covariance, the
    spread between the tone curves of ``MODEL_TERMS`` and the form's, ``MODEL_FORM_SIGMA``); None
    where it does not hold them or cannot be fitted (``found.model`` says why; the caller refuses
    N). ``measurement``: the stack's ``Measurement``, its profiles kept; ``table``: its first
    reading; ``options``: the CoC fit's; ``airy_px``: each setting's Airy scale at 550 nm from
    the plain fit (px), which the model holds where it reaches ``MODEL_AIRY_PX``; the edges are
    read once more at the scale of the f-number read through the model (the plain fit's is
    biased by the processing)."""
    from lensfit.estimators import tone
    from lensfit.fitting import fit
    from lensfit.fitting.refits import airy_per_setting

    kept = measurement.profiles or {}
    state, key = kept.get("state"), kept.get("key")
    encodings = {im.encoding for im in measurement.stack.images}
    if state is None or key is None or len(encodings) != 1 or len(table.edge_tasks) != len(table.samples):
        found.model = {"why": "the edges' profiles were not kept" if state is None else
                       "the images declare different encodings"}
        return None
    radius, batch, index = state[1], state[7], state[8]
    by_task = {(tuple(key[i][1]), tuple(key[i][2])): j for j, i in enumerate(index)}
    where = [by_task.get((tuple(float(v) for v in t.start_px), tuple(float(v) for v in t.end_px)))
             for t in table.edge_tasks]
    setting_of = {j: smp.setting for smp, j in zip(table.samples, where) if j is not None}
    radii = [radius[i] for i in index]

    def scales(per_setting: dict[str, float] | None) -> list[float] | None:
        if not per_setting or max(per_setting.values()) < MODEL_AIRY_PX:
            return None
        typical = sorted(per_setting.values())[len(per_setting) // 2]
        return [per_setting.get(setting_of.get(j, ""), typical) for j in range(len(batch))]

    def fitted_through(readings: Any) -> tuple[Any, Any]:
        through = _through(table, where, readings)
        return through, fit(through, **{**options, "spot_shape": "disk"})

    encoding, runs, held = next(iter(encodings)), [], scales(airy_px)
    for terms in MODEL_TERMS:
        fitted, readings = tone.fit(batch, radii, encoding, terms, held)
        through, result = fitted_through(readings)
        if _misfits(fitted):
            runs.append((fitted, readings, through, result))
            break  # (refused whatever the other curve reads)
        again = scales(airy_per_setting(result)) if held is not None else None
        if again is not None:  # (read again at the Airy scale of the N read through the model)
            readings = tone.read(fitted, batch, radii, encoding, again)
            through, result = fitted_through(readings)
        runs.append((fitted, readings, through, result))
    fitted, readings, through, result = runs[0]
    spread = math.nan if len(runs) < 2 else 0.0
    for label, quantities in result.settings.items() if len(runs) > 1 else ():
        mine, other = quantities.get("f_number"), runs[1][3].settings.get(label, {}).get("f_number")
        if mine is not None and mine.value and other is not None and other.value:
            spread = max(spread, abs(math.log(other.value / mine.value)))
        elif mine is not None and mine.value:  # (the other curve cannot read it: no agreement to show)
            spread = math.inf
    tone_rel = _shared_sigma(through, where, readings, fitted)
    found.model = {"tone_terms": fitted.terms, "tone_coefficients": [float(c) for c in fitted.shared[:fitted.terms]],
                   "encoding": encoding, "sharpening_amount": fitted.amount,
                   "sharpening_sigma_px": fitted.sigma_px, "chi2_reduced": fitted.chi2_reduced,
                   "misfit": fitted.misfit,
                   "edges": fitted.edges, "f_number_spread": spread if math.isfinite(spread) else None,
                   "f_number_model_sigma": tone_rel,
                   "airy_px": None if held is None else max(airy_px.values()),
                   "tone_curve": _curve_table(fitted)}
    if _misfits(fitted):
        found.model["why"] = (f"their profiles scatter about the model {math.sqrt(fitted.chi2_reduced):.1f} times "
                              f"their noise (reduced chi-square {fitted.chi2_reduced:.1f} > {MODEL_MAX_CHI2:g}), "
                              f"missing them by {100 * fitted.misfit:.2f} % of their contrast beyond it "
                              f"(> {100 * MODEL_MAX_MISFIT:g} %): "
                              "processing beyond a tone curve and an unsharp mask, such as noise reduction or "
                              "deconvolution sharpening")
        return None
    if spread > MODEL_MAX_SPREAD:
        found.model["why"] = (f"tone curves of {MODEL_TERMS[0]} and {MODEL_TERMS[1]} terms read N "
                              + (f"{100 * spread:.1f} % apart" if math.isfinite(spread) else "one not at all")
                              + f", more than {100 * MODEL_MAX_SPREAD:g} % apart")
        return None
    widening = math.hypot(spread, tone_rel, MODEL_FORM_SIGMA)
    for quantities in result.settings.values():
        for q in ("f_number", "f_number_effective", "aperture_diameter_mm", "aperture_diameter_effective_mm"):
            est = quantities.get(q)
            if est is not None and est.value is not None:
                quantities[q] = est.widened(widening, "processing")
    found.modelled = True
    result.warnings.append(
        f"the blur was read through a tone curve and sharpening fitted to the edges ({found.describe()}): "
        f"unsharp-mask amount {fitted.amount:.2f} at {fitted.sigma_px:.2f} px, reduced chi-square "
        f"{fitted.chi2_reduced:.2f} over {fitted.edges} edges; the f-number's interval carries the model's "
        f"uncertainty ({100 * widening:.1f} %, variance source processing). The RAW files give a tighter N")
    return through, result


def _misfits(fitted: Any) -> bool:
    """Whether the model misses a stack's profiles by more than their noise can explain (see
    ``MODEL_MAX_CHI2``, ``MODEL_MAX_MISFIT``)."""
    if not (math.isfinite(fitted.chi2_reduced) and math.isfinite(fitted.misfit)):
        return True
    return fitted.chi2_reduced > MODEL_MAX_CHI2 and fitted.misfit > MODEL_MAX_MISFIT


def _through(table: Any, where: list[int | None], readings: Any) -> Any:
    """``table`` with each sample's blur read through the processing model (``readings``, the
    edges' of ``where``); samples the model did not read, or whose window was truncated, get no
    value."""
    import dataclasses

    from lensfit.estimators.base import Flag

    dropped = (Flag.SHAPED_SPOT, Flag.RADIAL_PROFILE, Flag.MARKER_STRIPE)
    scales = table.blur_scale if len(table.blur_scale) == len(table.samples) else [1.0] * len(table.samples)
    samples = []
    for smp, j, scale in zip(table.samples, where, scales):
        flags = tuple(f for f in smp.flags if f not in dropped) + (Flag.PROCESSING_MODELLED,)
        if smp.coc_diameter_px is None:
            samples.append(smp)
            continue
        if j is None or not readings.ok[j] or Flag.WINDOW_TRUNCATED in smp.flags:
            samples.append(dataclasses.replace(smp, coc_diameter_px=None, sigma_px=None, flags=flags + (
                Flag.NOT_MEASURED,), disk_diameter_px=None, disk_sigma_px=None))
            continue
        rho, s_rho = float(readings.theta[j, 1]), float(readings.rho_sigma[j])
        R = math.sqrt(max(rho, 0.0))
        sigma = min(s_rho / R if R > 0 else math.inf, 2.0 * math.sqrt(s_rho))  # (c = 2 sqrt(rho))
        if not (math.isfinite(sigma) and 1e-6 < sigma < MAX_SIGMA_PX):  # a profile that does not determine it
            samples.append(dataclasses.replace(smp, coc_diameter_px=None, sigma_px=None, flags=flags + (
                Flag.BLUR_UNDETERMINED,), disk_diameter_px=None, disk_sigma_px=None))
            continue
        samples.append(dataclasses.replace(smp, coc_diameter_px=2.0 * R / scale, sigma_px=sigma / scale, flags=flags,
                                           disk_diameter_px=None, disk_sigma_px=None))
    return dataclasses.replace(table, samples=samples)


def _shared_sigma(table: Any, where: list[int | None], readings: Any, fitted: Any) -> float:
    """The f-number's relative uncertainty from the curve and mask's covariance: along each of its
    principal directions, one sigma moves every edge's reading; the blurs' weighted mean relative
    move (edges over 2 px, where N is read) is what N moves by, added in quadrature."""
    import numpy as np

    rows = [j for smp, j in zip(table.samples, where) if j is not None and smp.coc_diameter_px is not None
            and smp.sigma_px and smp.coc_diameter_px >= 2.0]
    if not rows:
        return 0.0
    rho = readings.theta[rows, 1]
    c = 2.0 * np.sqrt(np.maximum(rho, 1e-12))
    weight = (c / np.maximum(readings.rho_sigma[rows] / np.sqrt(np.maximum(rho, 1e-12)), 1e-12)) ** 2
    values, vectors = np.linalg.eigh(fitted.shared_cov)
    total = 0.0
    for value, vector in zip(values, vectors.T):
        moved = readings.rho_slope[rows] @ (vector * math.sqrt(max(value, 0.0))) / (2.0 * rho)  # d c / c
        total += float(np.sum(weight * moved) / np.sum(weight)) ** 2
    return math.sqrt(total)


def _curve_table(fitted: Any, points: int = 21) -> list[list[float]]:
    """The fitted tone curve as ``[light, file value, declared encoding's value]`` rows."""
    import numpy as np

    light = np.linspace(0.0, 1.0, points)
    curve, plain = fitted.curve(light), fitted.curve(light, warped=False)
    return [[float(a), float(b), float(c)] for a, b, c in zip(light, curve, plain)]
