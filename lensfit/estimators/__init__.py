"""Blur estimators: one module each, looked up by name.

An estimator is a function ``measure(image, tasks) -> list[BlurEstimate]``: given a linear
float64 image and the straight target edges seen in it (with their geometry), it returns the
blur-disk diameter at each edge with a 1-sigma uncertainty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from lensfit.errors import InputError


@dataclass(frozen=True)
class EdgeTask:
    """One straight target edge in one image.

    Attributes
    ----------
    start_px, end_px : (2,) projected end points (the edge runs between them)
    clear_left_px, clear_right_px : clean room on each side of the edge, in px (left = the side
        of the normal (-dy, dx) of start->end, in image coordinates)
    context : estimator-specific extras (the target, its pose and intrinsics)
    """

    start_px: np.ndarray
    end_px: np.ndarray
    clear_left_px: float
    clear_right_px: float
    context: dict[str, Any] = field(default_factory=dict, compare=False)


@dataclass(frozen=True)
class BlurEstimate:
    """``line_px``: the edge line as the image shows it (two points), where the estimator
    locates it; used to refine the target's corners for calibration."""

    coc_diameter_px: float | None
    sigma_px: float | None
    flags: tuple[str, ...] = ()
    pixels: int = 0
    rms_residual: float | None = None
    line_px: tuple[tuple[float, float], tuple[float, float]] | None = None


#: Model-error floor shared by the estimators: perspective across a segment and the limits of
#: any disk model make 0.3 % of c + 0.02 px the least uncertainty worth stating.
MODEL_FLOOR_REL = 0.003
MODEL_FLOOR_PX = 0.02


def with_model_floor(sigma_fit_px: float, coc_px: float) -> float:
    """The fit's 1 sigma combined in quadrature with the model-error floor."""
    return math.sqrt(sigma_fit_px**2 + (MODEL_FLOOR_REL * coc_px) ** 2 + MODEL_FLOOR_PX**2)


Estimator = Callable[[np.ndarray, list[EdgeTask]], list[BlurEstimate]]


def _edge(image, tasks):
    from lensfit.estimators.edge import measure

    return measure(image, tasks)


def _edge_disk(image, tasks):
    from lensfit.estimators.edge import measure

    return measure(image, tasks, second_moment=False)


def _target(image, tasks):
    from lensfit.estimators.target import measure

    return measure(image, tasks)


#: Registry: name -> (measure function, one-line description).
ESTIMATORS: dict[str, tuple[Estimator, str]] = {
    "edge": (_edge, "slanted-edge ESF: second-moment blur diameter (a uniform-disk fit, corrected by the "
                    "profile's own second moment; right for aberrated spots; fast)"),
    "edge-disk": (_edge_disk, "slanted-edge ESF fit of a uniform disk, its diameter (biased low on aberrated "
                              "spots; the estimator before the second-moment correction)"),
    "target": (_target, "analysis by synthesis of the known target texture (slower, uses every pixel)"),
}


def get_estimator(name: str) -> Estimator:
    """The estimator called ``name``; an unknown name lists the valid ones."""
    if name not in ESTIMATORS:
        raise InputError("estimator", name, "one of: " + ", ".join(ESTIMATORS))
    return ESTIMATORS[name][0]
