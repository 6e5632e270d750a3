"""What every blur estimator shares: the task (one edge), the estimate and its flags, the
model-error floor."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np


class Flag(StrEnum):
    """How an edge's blur was read, or why it was not: a sample's ``flags`` (an ordered tuple of
    these, written ``;``-separated in the samples files and read back as written). Each is its own string
    value, so a flag read back from a file compares equal to its member."""

    #: within 2 degrees of a pixel axis: little super-sampling, unreliable below about 2 px
    AXIS_ALIGNED = "axis_aligned"
    #: the profile does not determine the blur (no value)
    BLUR_UNDETERMINED = "blur_undetermined"
    #: the clean room around the edge is narrower than the spot's reach (no value, unless read
    #: across a marker's stripe)
    WINDOW_TRUNCATED = "window_truncated"
    #: the edge is too short for a profile of its own length
    SHORT_EDGE = "short_edge"
    #: too few pixels in the edge's window (no value)
    TOO_FEW_PIXELS = "too_few_pixels"
    #: the levels on the two sides differ too little for a reading
    LOW_CONTRAST = "low_contrast"
    #: the profile's fit did not converge (no value)
    FIT_FAILED = "fit_failed"
    #: the edge was not measured (no estimate came back for it)
    NOT_MEASURED = "not_measured"
    #: the target estimator: no pose for the target (no value)
    NO_POSE = "no_pose"
    #: the target estimator: the cost is flat in the blur (no value)
    FLAT_COST = "flat_cost"
    #: a blur below a pixel, read only where a 1 px blur fits clearly worse
    SUB_PIXEL_BLUR = "sub_pixel_blur"
    #: the spot read as two disks (a core in a halo, a bright rim): its second moment
    SHAPED_SPOT = "shaped_spot"
    #: a spot two disks cannot hold, read as a radial profile
    RADIAL_PROFILE = "radial_profile"
    #: read across a ChArUco marker's light stripe into its black border
    MARKER_STRIPE = "marker_stripe"
    #: the reading divided by the lens distortion's stretch across the edge
    DISTORTION_SCALED = "distortion_scaled"
    #: the distortion's stretch is beyond the range the correction is trusted over
    DISTORTION_EXTREME = "distortion_extreme"
    #: read through the Airy pattern: the defocus blur alone
    DIFFRACTION_MODELLED = "diffraction_modelled"
    #: read through the tone curve and sharpening fitted to the stack's edges (a developed image;
    #: ``lensfit.measurement.processing``)
    PROCESSING_MODELLED = "processing_modelled"
    #: the pipeline's diffraction test found no Airy pattern in these images: the spots' shapes
    #: are the lens's
    AIRY_NOT_SEEN = "airy_not_seen"
    #: the target's pose has two solutions that fit about equally well
    POSE_AMBIGUOUS = "pose_ambiguous"


def flags_from_text(text: str) -> tuple[Flag, ...]:
    """A samples file's ``;``-separated flags as members, in order (ValueError names an unknown one)."""
    out: list[Flag] = []
    for name in filter(None, (part.strip() for part in text.split(";"))):
        try:
            out.append(Flag(name))
        except ValueError:
            raise ValueError(f"flag {name!r} is not one lensfit writes (known: {', '.join(Flag)})") from None
    return tuple(out)


@dataclass(frozen=True)
class EdgeTask:
    """One straight target edge in one image.

    Attributes
    ----------
    start_px, end_px : (2,) projected end points (the edge runs between them)
    clear_left_px, clear_right_px : clean room on each side of the edge, in px (left = the side
        of the normal (-dy, dx) of start->end, in image coordinates)
    context : estimator-specific extras (the target, its pose and intrinsics)
    border_left_px, border_right_px : beyond the clean room, a dark band this wide (px) before the
        target's pattern goes on (a ChArUco marker's black border); 0 where nothing is known
    """

    start_px: np.ndarray
    end_px: np.ndarray
    clear_left_px: float
    clear_right_px: float
    context: dict[str, Any] = field(default_factory=dict, compare=False)
    border_left_px: float = 0.0
    border_right_px: float = 0.0


@dataclass(frozen=True)
class BlurEstimate:
    """``line_px``: the edge line as the image shows it (two points), where the estimator
    locates it; used to refine the target's corners for calibration. ``rms_residual``: the RMS
    residual, in standard errors, of the estimator's uniform-disk profile (through the Airy pattern
    where diffraction is modelled), also where the reading is another profile's.
    ``disk_diameter_px``, ``disk_sigma_px``: where the reading is not the uniform disk's (the
    ``edge`` estimator's shaped spot), the uniform disk's reading of the same edge and its sigma.
    ``line_cov_px2``: where ``line_px`` is given, the covariance (px^2) of its offsets across the
    edge at its two points: (variance at the first, covariance, variance at the second).
    ``bright_side``: where ``line_px`` is given, the unit normal of the edge toward its bright
    side (image coordinates): with the task's line it says how far the edge lies from the
    target's corners toward its bright side, which a tone response the image's declared encoding
    does not undo moves (``lensfit.measurement.processing``)."""

    coc_diameter_px: float | None
    sigma_px: float | None
    flags: tuple[Flag, ...] = ()
    pixels: int = 0
    rms_residual: float | None = None
    line_px: tuple[tuple[float, float], tuple[float, float]] | None = None
    disk_diameter_px: float | None = None
    disk_sigma_px: float | None = None
    line_cov_px2: tuple[float, float, float] | None = None
    bright_side: tuple[float, float] | None = None


#: Model-error floor shared by the estimators: perspective across a segment and the limits of
#: any disk model make 0.3 % of c + 0.02 px the least uncertainty worth stating.
MODEL_FLOOR_REL = 0.003
MODEL_FLOOR_PX = 0.02


def with_model_floor(sigma_fit_px: float, coc_px: float) -> float:
    """The fit's 1 sigma combined in quadrature with the model-error floor."""
    return math.sqrt(sigma_fit_px**2 + (MODEL_FLOOR_REL * coc_px) ** 2 + MODEL_FLOOR_PX**2)
