"""Each focus setting's calibration from the targets its images show: misdetected views and
settings too thinly seen to calibrate left out, by name."""

from __future__ import annotations

from typing import Any

from lensfit.calibration.camera import (MIN_POINTS, MIN_VIEWS, calibrate, known_intrinsics, outlier_views,
                                       usable_views)
from lensfit.calibration.targets import Detection
from lensfit.io.samples import SampleTable
from lensfit.io.stack import Stack


def calibrate_views(stack: Stack, detections: dict[int, list[Detection]], table: SampleTable,
                    final: bool = True) -> dict[str, Any]:
    """Each setting's intrinsics from its views in ``detections`` (image index: its targets; given
    intrinsics as given). Views whose corners reproject far off their setting's calibration are
    misdetections, and settings seen in too few views to calibrate (where others can be) are
    left out (:func:`leave_out_uncalibrated`): both taken out of ``detections``, with a warning
    in ``table``. ``final``: the focal lengths' sigmas by the jackknife (else OpenCV's own)."""
    views: dict[str, list[tuple[int, Detection]]] = {}
    for i in range(len(stack.images)):
        views.setdefault(stack.images[i].setting, []).extend((i, d) for d in detections[i])
    known = {k: known_intrinsics(v, stack.shape) for k, v in stack.intrinsics.items()}
    todo = {k: v for k, v in views.items() if k not in known and k not in table.left_out_settings}
    leave_out_uncalibrated(stack, detections, table, todo, len(known))
    for label, bad in outlier_views({k: [d for _, d in v] for k, v in todo.items()}, stack.shape).items():
        for j, rms, median in bad:  # misdetections: left out of the calibration and the samples
            i, det = todo[label][j]
            detections[i] = [d for d in detections[i] if d is not det]
            table.warnings.append(
                f"{stack.images[i].file.name}: target {det.target_id!r} left out, its corners reproject "
                f"{rms:.2g} px off the calibration of setting {label!r} (median view {median:.2g} px): a "
                "misdetection, or markers misread under heavy blur")
        dropped = {j for j, _, _ in bad}
        todo[label] = [view for j, view in enumerate(todo[label]) if j not in dropped]
    views_of = {k: [d for _, d in v] for k, v in todo.items()}
    return {**(calibrate(views_of, stack.shape, jackknife=final) if views_of else {}), **known}


def leave_out_uncalibrated(stack: Stack, detections: dict[int, list[Detection]], table: SampleTable,
                           todo: dict[str, list[tuple[int, Detection]]], known: int) -> None:
    """Settings of ``todo`` (label: its views) with too few usable views to calibrate, where
    other settings (``known`` with given intrinsics among them) can be: left out, their images'
    targets with them, by name in ``table.left_out_settings`` and its warnings (the others are
    fitted; the results refuse these). Where none can be, the calibration refuses the stack
    naming the first."""
    short = {k: usable_views([d for _, d in v]) for k, v in todo.items()}
    short = {k: c for k, c in short.items() if c < MIN_VIEWS}
    if not short or len(short) == len(todo) + known:
        return
    for label, count in short.items():
        why = (f"seen in {count} image(s) with {MIN_POINTS}+ detected corners, and its calibration needs "
               f"{MIN_VIEWS}: add views of the targets (some tilted by 20-40 degrees) in this setting, with "
               "less blur (targets nearer its focus distance, or the aperture closed) where they were not found")
        table.left_out_settings[label] = why
        table.warnings.append(f"setting {label!r} left out: {why}")
        del todo[label]
        for i, entry in enumerate(stack.images):
            if entry.setting == label:
                detections[i] = []
