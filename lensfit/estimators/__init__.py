"""Blur estimators: one module each, looked up by name.

An estimator is a function ``measure(image, tasks) -> list[BlurEstimate]``: given a linear
float64 image and the straight target edges seen in it (with their geometry), it returns the
blur-disk diameter at each edge with a 1-sigma uncertainty.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from lensfit.errors import InputError


from lensfit.estimators.base import MODEL_FLOOR_PX, MODEL_FLOOR_REL, BlurEstimate, EdgeTask, with_model_floor

__all__ = ["BlurEstimate", "EdgeTask", "Estimator", "ESTIMATORS", "get_estimator", "with_model_floor",
           "MODEL_FLOOR_PX", "MODEL_FLOOR_REL"]

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
