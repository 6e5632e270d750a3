"""Samples in, in the solver's terms: validation, per-setting calibration, depth along each edge."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from lensfit.estimators.base import Flag
from lensfit.errors import InputError
from lensfit.fitting.constants import (BLUR_SCALE_SIGMA_SHAPED, DISTANCE_RANGE_MM, MAX_BLUR_PX, MAX_FOCAL_LENGTH_PX,
                                   MIN_SIGMA_PX, PIXEL_PITCH_RANGE_MM, SHAPE_ERROR_SHARE, SHAPE_ERROR_SHARE_RADIAL,
                                   SHAPE_SCALE_SHARE, UNREAD_SHAPE_MIN, NODES_T, disk_scale_sigma)
from lensfit.io.samples import Sample, SampleTable


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
    #: True where the sample's distances come from a target pose solved with its setting's
    #: calibrated focal length (``distance_source`` "pose"): they scale with that calibration's
    #: error, which the fit carries (lensfit.fitting.model._distance_scale)
    pose: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    #: the estimator's shared scale error that applies to each sample (relative 1 sigma;
    #: BLUR_SCALE_SIGMA and BLUR_SCALE_BIAS_PX2 / c^2 in quadrature, more for a ``shaped_spot`` reading:
    #: ``_scale_sigma``)
    scale_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: of ``dropped``, the edges whose blur outgrew the clean room around them (flag
    #: ``window_truncated``)
    dropped_truncated: int = 0
    #: each sample's squared field, ``(field_radius_px / f_px)^2`` (the tangent of its field angle,
    #: squared), where its field radius and its setting's focal length in px are known; NaN where
    #: not (lensfit.fitting.model: field curvature)
    field2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: True where the sample was read through the shaped-spot model and gives the uniform disk's
    #: reading too; whether the images were read through the Airy pattern or found without one
    #: (flags ``diffraction_modelled``, ``airy_not_seen``; lensfit.fitting.refits)
    shaped: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    airy_checked: bool = False
    #: each kept shaped reading's relative model error (1 sigma), NaN where the reading is not
    #: shaped: a share of its relative difference from the uniform disk's reading of the same edge
    #: (:func:`_shape_error`; lensfit.fitting.uncertainty.arms_part)
    shape_error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: per setting, the degrees of freedom of ``focal_length_sigma_px``: the views less one where a
    #: leave-one-view-out jackknife estimated it from few views; inf where its form is known (the
    #: corners' covariance from some hundred residuals, a stated sigma)
    focal_length_dof: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: per setting (label: share, readings), where its resolved spots are visibly no uniform
    #: disks: the model error carried by its readings whose shape was not read
    #: (:func:`_unread_shape_sigma`)
    unread_shape: dict[str, tuple[float, int]] = field(default_factory=dict)

    def blur_scale_sigma(self, weights: np.ndarray | None = None) -> float:
        """The estimator's shared relative scale error for this fit: each sample's weighted by
        the information it carries about a scale, ``(c / sigma)^2`` (times ``weights``)."""
        info = (self.coc_px / self.sigma_px) ** 2 * (1.0 if weights is None else weights)
        total = float(np.sum(info))
        return float(np.sum(info * self.scale_sigma) / total) if total > 0 else 0.0


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


#: The flags of a reading through a spot's shape, which a uniform disk's reading of the same edge
#: taken instead no longer has.
SHAPE_READ = frozenset({Flag.SHAPED_SPOT, Flag.RADIAL_PROFILE, Flag.MARKER_STRIPE})


def samples_from(samples: Any) -> tuple[list[Sample], dict[str, Any]]:
    """Samples (typed) and context (pixel pitch, intrinsics) from any accepted input: a
    :class:`SampleTable`, a samples file, or a sequence of :class:`Sample` or of mappings of their
    columns (:meth:`Sample.from_row`)."""
    if isinstance(samples, (str, Path)):
        samples = SampleTable.read(samples)
    if isinstance(samples, SampleTable):
        ctx = {"pixel_pitch_mm": samples.pixel_pitch_mm,
               "focal_length_px": {k: v.focal_length_px for k, v in samples.intrinsics.items()},
               "focal_length_sigma_px": {k: v.focal_length_sigma_px for k, v in samples.intrinsics.items()},
               # a jackknife's degrees of freedom, or those a model's sigma from too few views for
               # one is worth (lensfit.calibration.camera.MODEL_PRIOR_DOF); else a Gaussian sigma
               "focal_length_dof": {k: (v.focal_length_sigma_dof or float(max(v.views - 1, 1)))
                                    if v.focal_length_sigma_method == "jackknife"
                                    else (v.focal_length_sigma_dof or math.inf) if v.source == "calibrated"
                                    else math.inf for k, v in samples.intrinsics.items()},
               # settings whose calibration fitted no lens distortion, and those whose did (their
               # readings taken through it where flagged distortion_scaled; lensfit.fitting.constants:
               # BLUR_SCALE_SIGMA_PLAIN); intrinsics given or read back from a CSV do not say
               "undistorted": {k for k, v in samples.intrinsics.items()
                               if v.source == "calibrated" and not any(v.distortion)},
               "distorted": {k for k, v in samples.intrinsics.items()
                             if v.source == "calibrated" and any(v.distortion)}}
        return list(samples.samples), ctx
    out = []
    for i, s in enumerate(samples):
        if isinstance(s, Sample):
            out.append(s)
            continue
        try:
            out.append(Sample.from_row(s if isinstance(s, Mapping) else vars(s)))
        except InputError as exc:
            raise InputError(f"samples[{i}].{exc.argument}", exc.value, exc.requirement, exc.hint) from None
        except TypeError:
            raise InputError(f"samples[{i}]", s, "a Sample, or a mapping of its columns by name") from None
    return out, {}


#: Focus settings one fit takes at most: a photographer's bracket has a few, a careful study some
#: dozens; the fit's cost grows with the square of their number.
MAX_SETTINGS = 100


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
            focal_length_sigma_px: float | dict[str, float] | None = None,
            disk_readings: Any = ()) -> FitData:
    """Validate samples and turn them into :class:`FitData` (see :func:`fit`). ``disk_readings``:
    the settings (labels; True: all) whose samples read through the shaped-spot model are taken
    at the uniform disk's reading where they give it (``disk_diameter_px``, ``disk_sigma_px``)."""
    rows, ctx = samples_from(samples)
    shaped = [i for i, r in enumerate(rows) if Flag.SHAPED_SPOT in r.flags and r.disk_diameter_px is not None
              and r.disk_sigma_px is not None and r.coc_diameter_px is not None]
    swap = [i for i in shaped if disk_readings is True or rows[i].setting in disk_readings]
    kept = set(shaped) - set(swap)  # shaped readings that stay so
    for i in swap:
        rows[i] = dataclasses.replace(rows[i], coc_diameter_px=rows[i].disk_diameter_px, sigma_px=rows[i].disk_sigma_px,
                                      flags=tuple(f for f in rows[i].flags if f not in SHAPE_READ))
    pitch = _pixel_pitch(pixel_pitch_mm, ctx.get("pixel_pitch_mm"))
    used, used_rows, dropped, truncated = [], [], 0, 0
    for i, r in enumerate(rows):
        c, sg, d = r.coc_diameter_px, r.sigma_px, r.distance_mm
        if not (math.isfinite(d) and d > 0):
            raise InputError(f"samples[{i}].distance_mm", d, "> 0 mm and finite")
        if not DISTANCE_RANGE_MM[0] <= d <= DISTANCE_RANGE_MM[1]:
            raise InputError(f"samples[{i}].distance_mm", d, f"between {DISTANCE_RANGE_MM[0]:g} and "
                             f"{DISTANCE_RANGE_MM[1]:g} mm", "distances are in mm from the lens")
        _check_optional(i, r)
        if c is not None and sg is not None and (c < 0 or sg <= 0):
            bad = "coc_diameter_px" if c < 0 else "sigma_px"
            raise InputError(f"samples[{i}].{bad}", getattr(r, bad), "> 0 px" if bad == "sigma_px" else ">= 0 px",
                             "a blur diameter and its sigma are never negative; leave both empty where an edge has "
                             "no measurement")
        if c is None or sg is None or not (math.isfinite(c) and math.isfinite(sg) and sg > 0 and c >= 0):
            dropped += 1  # the estimator could not measure this edge
            truncated += Flag.WINDOW_TRUNCATED in r.flags
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
        if truncated:  # the edges were found, and every blur outgrew its window
            fix = (f"{truncated} of them flagged window_truncated: the blur outgrew the clean room around each "
                   "edge; stop down, bring the targets nearer the focus distance, or use a target with larger "
                   "squares")
        elif rows:
            fix = "the estimator read no edge's blur (each sample's flags say why)"
        else:
            fix = "measure a stack whose targets were detected (lensfit measure)"
        raise InputError("samples", f"{len(rows)} rows", "at least one sample with a measured coc_diameter_px and "
                         "sigma_px", fix)
    labels = sorted({r.setting for r in used})
    if len(labels) > MAX_SETTINGS:
        raise InputError("samples.setting", f"{len(labels)} labels", f"at most {MAX_SETTINGS} focus settings in one "
                         "fit (each adds its own parameters)", "fit the settings in groups, or check the setting column")
    idx = {k: i for i, k in enumerate(labels)}
    dist = np.array([r.distance_mm for r in used])
    d0 = np.array([r.distance_start_mm for r in used])
    d1 = np.array([r.distance_end_mm for r in used])
    w_mean, _ = inverse_distance_moments(d0, d1)
    w_nodes = 1.0 / (d0[:, None] + NODES_T[None, :] * (d1 - d0)[:, None])
    fpx = _per_setting(focal_length_px if focal_length_px is not None else ctx.get("focal_length_px"),
                       labels, "focal_length_px", math.nan)
    fsg = _per_setting(focal_length_sigma_px if focal_length_sigma_px is not None
                       else ctx.get("focal_length_sigma_px"), labels, "focal_length_sigma_px", 0.0)
    fdof = (np.full(len(labels), math.inf) if focal_length_sigma_px is not None else
            _per_setting(ctx.get("focal_length_dof"), labels, "focal_length_dof", math.inf))
    bad = ~(np.isnan(fpx) | ((fpx >= 1.0) & (fpx <= MAX_FOCAL_LENGTH_PX)))
    if bad.any():
        raise InputError("focal_length_px", float(fpx[bad][0]), f"between 1 and {MAX_FOCAL_LENGTH_PX:g} px")
    bad = ~np.isfinite(fsg) | (fsg < 0) | (fsg > MAX_FOCAL_LENGTH_PX)
    if bad.any():
        raise InputError("focal_length_sigma_px", float(fsg[bad][0]), f"between 0 and {MAX_FOCAL_LENGTH_PX:g} px")
    sigma, unread_share = _unread_shape_sigma(used, labels)
    images = [r.image for r in used]  # "" = not known: no jackknife over images
    image_index = {name: (i if name else -1) for i, name in enumerate(dict.fromkeys(images))}
    return FitData(labels, np.array([idx[r.setting] for r in used]), dist, w_mean, w_nodes,
                   np.array([r.coc_diameter_px for r in used]),
                   sigma, float(pitch), fpx, fsg, dropped,
                   np.array([image_index[name] for name in images], int), np.array(used_rows, int),
                   np.array([r.distance_source == "pose" for r in used], bool),
                   np.array([_scale_sigma(r, ctx.get("undistorted", frozenset()), ctx.get("distorted", frozenset()))
                             for r in used]), truncated,
                   _field2(used, [fpx[idx[r.setting]] for r in used]),
                   np.array([i in kept for i in used_rows], bool),
                   any({Flag.DIFFRACTION_MODELLED, Flag.AIRY_NOT_SEEN} & set(r.flags) for r in rows),
                   np.array([_shape_error(r) if i in kept else math.nan for i, r in zip(used_rows, used)]),
                   fdof, unread_share)


#: The optional numbers of a sample and the ranges they must lie in (closed; the lower bound of
#: a sigma is above 0).
OPTIONAL_RANGES = {"distance_start_mm": DISTANCE_RANGE_MM, "distance_end_mm": DISTANCE_RANGE_MM,
                   "field_radius_px": (0.0, MAX_BLUR_PX), "disk_diameter_px": (0.0, MAX_BLUR_PX),
                   "disk_sigma_px": (MIN_SIGMA_PX, MAX_BLUR_PX)}


def _check_optional(i: int, row: Sample) -> None:
    """A sample's optional numbers (the edge's ends, its field radius, the uniform disk's reading)
    finite and in range where given: each is used, and a wrong one would bias the fit silently."""
    for name, (lo, hi) in OPTIONAL_RANGES.items():
        value = getattr(row, name)
        if value is not None and not lo <= value <= hi:  # (NaN is out)
            unit = name.rsplit("_", 1)[1]
            raise InputError(f"samples[{i}].{name}", value, f"a finite number between {lo:g} and {hi:g} {unit}",
                             "write samples with lensfit measure, or leave the field out")
    for name in ("start_px", "end_px"):
        value = getattr(row, name)
        if not all(abs(v) <= MAX_BLUR_PX for v in value):  # (NaN is out)
            raise InputError(f"samples[{i}].{name}", value, f"two finite pixel coordinates within {MAX_BLUR_PX:g} px",
                             "write samples with lensfit measure, or leave the field out")


def _field2(rows: list[Sample], fpx: list[float]) -> np.ndarray:
    """``(field_radius_px / f_px)^2`` per row (radii checked by :func:`_check_optional`), NaN
    where either is unknown."""
    out = np.full(len(rows), math.nan)
    for i, (r, f) in enumerate(zip(rows, fpx)):
        if r.field_radius_px is not None and math.isfinite(f):
            out[i] = (r.field_radius_px / f) ** 2
    return out


def _scale_sigma(row: Sample, undistorted: set[str] = frozenset(), distorted: set[str] = frozenset()) -> float:
    """The estimator's shared scale error for one reading: the uniform disk's, and for a shaped
    spot's reading ``SHAPE_SCALE_SHARE`` of its relative difference from the uniform disk's beside
    it, in quadrature (an independent source)
    (``BLUR_SCALE_SIGMA_SHAPED`` where samples written by an older lensfit do not give that). The
    constant is ``BLUR_SCALE_SIGMA_PLAIN`` where the reading is plain: not through the Airy
    model, in a setting of ``undistorted`` (calibrated, no lens distortion found), or of
    ``distorted`` (calibrated with lens distortion) and taken through it (flag
    ``distortion_scaled``: ``lensfit.measurement.measure``)."""
    c, flags, setting = row.coc_diameter_px, row.flags, row.setting
    plain = Flag.DIFFRACTION_MODELLED not in flags and (
        setting in undistorted or (setting in distorted and Flag.DISTORTION_SCALED in flags))
    if Flag.SHAPED_SPOT not in flags:
        return disk_scale_sigma(c, plain)
    departure = _departure(row)
    if departure is None:
        return BLUR_SCALE_SIGMA_SHAPED
    return math.hypot(disk_scale_sigma(c, plain), SHAPE_SCALE_SHARE * departure)


def _departure(row: Sample) -> float | None:
    """A shaped reading's relative difference from the uniform disk's reading of the same edge,
    ``|c - disk| / c``; None where the reading is not shaped or gives no disk reading."""
    c, disk = row.coc_diameter_px, row.disk_diameter_px
    if Flag.SHAPED_SPOT not in row.flags or disk is None or not math.isfinite(disk) or c <= 0:
        return None
    return abs(c - disk) / c


def _pixel_pitch(given: float | None, stated: Any) -> float:
    """The pixel pitch (mm): the argument, else the samples' own; checked."""
    stated = None if isinstance(stated, float) and math.isnan(stated) else stated  # (a table without one)
    pitch = given if given is not None else stated
    # (named as the samples' own field where the value came from them, not the argument)
    field = "pixel_pitch_mm" if given is not None or stated is None else "samples.pixel_pitch_mm"
    if pitch is None or not (isinstance(pitch, (int, float)) and math.isfinite(pitch) and pitch > 0):
        raise InputError(field, pitch, "> 0 mm", "give the sensor's pixel pitch (stack.toml [camera])")
    if not PIXEL_PITCH_RANGE_MM[0] <= pitch <= PIXEL_PITCH_RANGE_MM[1]:
        raise InputError(field, pitch, f"between {PIXEL_PITCH_RANGE_MM[0]:g} and {PIXEL_PITCH_RANGE_MM[1]:g} "
                         "mm (0.1 micrometre to 1 mm)", "pixel pitches are given in mm, e.g. 0.0059 for 5.9 um")
    return pitch


def _shape_error(row: Sample) -> float:
    """A shaped reading's relative model error (1 sigma): ``SHAPE_ERROR_SHARE`` (two disks) or
    ``SHAPE_ERROR_SHARE_RADIAL`` (flag ``radial_profile``: the data rejected two disks; or
    ``marker_stripe``: read across a marker's stripe, where the symmetric profiles missed the
    spot's reach) of its relative difference from the uniform disk's reading of the same edge."""
    departure = _departure(row)
    radial = {Flag.RADIAL_PROFILE, Flag.MARKER_STRIPE} & set(row.flags)
    share = SHAPE_ERROR_SHARE_RADIAL if radial else SHAPE_ERROR_SHARE
    return math.nan if departure is None else share * departure


def _unread_shape_sigma(used: list[Sample], labels: list[str]) -> tuple[np.ndarray, dict]:
    """Each reading's sigma, and per setting the model error its readings of unread shape carry.

    The uniform disk reads a real lens's spot (a core in a halo, a bright rim) small: by up to a
    fifth on a 2 px core-and-halo spot along a pixel axis, where the profile is sampled once per
    pixel and the two-disk model cannot tell the shape (``lensfit.estimators.edge.SHAPE_MIN_PX``).
    Where a setting's resolved spots show how far from uniform disks they are (at least
    ``UNREAD_SHAPE_MIN`` shaped readings; ``m`` the median relative difference from the disk's
    reading of the same edge over the ``UNREAD_SHAPE_MIN`` nearest in inverse distance on either
    side, the larger), the readings whose shape was not read (no flag
    ``shaped_spot``; not through the Airy pattern, whose shape is the pattern's; not sub-pixel,
    stated with 0.2 px already) carry ``m c`` in quadrature with their sigma. On a uniform disk
    ``m`` is the noise's few tenths of a percent and changes nothing; on a retrofocus at f/4 (m
    about 10 %) the readings near the focus, 2 px cores in a halo along the pixel axes read 15-25 %
    small, took the focus distance 1.1 % long at 2.4 of its sigmas."""
    sigma = np.array([r.sigma_px for r in used])
    out: dict[str, tuple[float, int]] = {}
    setting = np.array([r.setting for r in used])
    w = np.array([1.0 / r.distance_mm for r in used])
    departure = np.array([_departure(r) for r in used], dtype=float)  # NaN: no shape read
    is_shaped = np.isfinite(departure)
    read_shaped = {Flag.SHAPED_SPOT, Flag.DIFFRACTION_MODELLED, Flag.SUB_PIXEL_BLUR}
    unread = np.array([not read_shaped & set(r.flags) for r in used])
    c = np.array([r.coc_diameter_px for r in used])
    for label in labels:
        mine = setting == label
        resolved = np.flatnonzero(mine & is_shaped)
        which = np.flatnonzero(mine & unread)
        if len(resolved) < UNREAD_SHAPE_MIN or not len(which):
            continue
        order = resolved[np.argsort(w[resolved])]
        w_sorted = w[order]
        rel = departure[order]
        # the nearest resolved spots in inverse distance on either side (the reading may lie on
        # either side of the focus, whose spots differ): the larger of their medians
        at = np.searchsorted(w_sorted, w[which])
        shares = np.array([max(float(np.median(rel[max(k - UNREAD_SHAPE_MIN, 0):k])) if k > 0 else 0.0,
                               float(np.median(rel[k:k + UNREAD_SHAPE_MIN])) if k < len(rel) else 0.0)
                           for k in at])
        sigma[which] = np.hypot(sigma[which], shares * c[which])
        out[label] = (float(np.median(shares)), len(which))
    return sigma, out
