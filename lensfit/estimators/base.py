"""What every blur estimator shares: the task (one edge), the estimate, the model-error floor."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


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
    edge at its two points: (variance at the first, covariance, variance at the second)."""

    coc_diameter_px: float | None
    sigma_px: float | None
    flags: tuple[str, ...] = ()
    pixels: int = 0
    rms_residual: float | None = None
    line_px: tuple[tuple[float, float], tuple[float, float]] | None = None
    disk_diameter_px: float | None = None
    disk_sigma_px: float | None = None
    line_cov_px2: tuple[float, float, float] | None = None


#: Model-error floor shared by the estimators: perspective across a segment and the limits of
#: any disk model make 0.3 % of c + 0.02 px the least uncertainty worth stating.
MODEL_FLOOR_REL = 0.003
MODEL_FLOOR_PX = 0.02


def with_model_floor(sigma_fit_px: float, coc_px: float) -> float:
    """The fit's 1 sigma combined in quadrature with the model-error floor."""
    return math.sqrt(sigma_fit_px**2 + (MODEL_FLOOR_REL * coc_px) ** 2 + MODEL_FLOOR_PX**2)
