"""From an image stack to samples of (distance from the lens, blur-disk diameter, uncertainty).

Pipeline: read the manifest -> detect every target in every image -> calibrate intrinsics per
lens setting (focal length in px; shared principal point and distortion) -> pose of each
target in each image -> the straight edges of each target, with the distance of their ends and
middle from the lens plane -> a blur estimator on each edge.

``measure(stack)`` returns a :class:`SampleTable`; the CLI writes it as CSV or JSON.
"""

from __future__ import annotations

import csv
import json

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit.calibration import Intrinsics, TargetPose, calibrate, estimate_pose, project
from lensfit.errors import SpecError
from lensfit.estimators import EdgeTask, get_estimator
from lensfit.stack import Stack, load_stack
from lensfit.targets import Detection, Target

SATURATION_LEVEL = 0.995
SATURATED_FRACTION_LIMIT = 0.01


@dataclass(frozen=True)
class Sample:
    """One blur measurement on one target edge in one image."""

    image: str
    setting: str
    target: str
    edge: str
    distance_mm: float  # of the edge's middle, from the lens plane
    distance_start_mm: float
    distance_end_mm: float
    coc_diameter_px: float | None
    sigma_px: float | None
    estimator: str
    flags: str  # ";"-separated
    start_px: tuple[float, float]
    end_px: tuple[float, float]
    distance_source: str  # "pose" or "manifest"


@dataclass
class SampleTable:
    """Samples plus what was learnt on the way (intrinsics, poses, detections)."""

    samples: list[Sample] = field(default_factory=list)
    intrinsics: dict[str, Intrinsics] = field(default_factory=dict)
    poses: dict[tuple[str, str], TargetPose] = field(default_factory=dict)
    pixel_pitch_mm: float = float("nan")
    image_shape: tuple[int, int] = (0, 0)
    warnings: list[str] = field(default_factory=list)

    COLUMNS = ("image", "setting", "target", "edge", "distance_mm", "coc_diameter_px", "sigma_px", "estimator",
               "flags", "distance_start_mm", "distance_end_mm", "start_px", "end_px", "distance_source")

    def __len__(self) -> int:
        return len(self.samples)

    def valid(self) -> list[Sample]:
        """Samples with a measured diameter."""
        return [s for s in self.samples if s.coc_diameter_px is not None]

    def column(self, name: str) -> np.ndarray:
        return np.array([getattr(s, name) for s in self.samples])

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for s in self.samples:
            row = asdict(s)
            row["start_px"], row["end_px"] = list(s.start_px), list(s.end_px)
            out.append({k: row[k] for k in self.COLUMNS})
        return out

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "samples": self.rows(),
            "pixel_pitch_mm": self.pixel_pitch_mm,
            "image_shape_px": list(self.image_shape),
            "intrinsics": {k: {**asdict(v), "principal_point_px": list(v.principal_point_px),
                               "distortion": list(v.distortion)} for k, v in self.intrinsics.items()},
            "warnings": self.warnings,
        }

    def write(self, path: str | Path) -> None:
        """CSV (``.csv``) or JSON (``.json``) by suffix."""
        path = Path(path)
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps(self.to_json_dict(), indent=1, allow_nan=False))
            return
        with path.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=self.COLUMNS)
            writer.writeheader()
            for row in self.rows():
                row = dict(row)
                row["start_px"] = f"{row['start_px'][0]:.3f} {row['start_px'][1]:.3f}"
                row["end_px"] = f"{row['end_px'][0]:.3f} {row['end_px'][1]:.3f}"
                writer.writerow({k: ("" if v is None else v) for k, v in row.items()})


def _check_saturation(stack: Stack, index: int, image: np.ndarray, det: Detection) -> None:
    pts = det.image_points_px
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int)
    region = image[max(y0, 0):y1 + 1, max(x0, 0):x1 + 1]
    if region.size and np.mean(region >= SATURATION_LEVEL) > SATURATED_FRACTION_LIMIT:
        raise SpecError(stack.images[index].file, "", f"{100 * np.mean(region >= SATURATION_LEVEL):.1f}% of the "
                        f"pixels on target {det.target_id!r} are saturated; expose less (blur cannot be measured "
                        "on clipped edges)")


def _edge_tasks(target: Target, det: Detection, pose: TargetPose, intr: Intrinsics):
    """Tasks for the target's edges whose both end corners were detected."""
    seen = set(int(i) for i in det.ids)
    out = []
    for seg in target.edges():
        if target.kind != "slanted-edge" and not (seg.corner_ids[0] in seen and seg.corner_ids[1] in seen):
            continue
        a, b = np.array(seg.start_mm), np.array(seg.end_mm)
        ends_cam = pose.to_camera(np.array([a, (a + b) / 2, b]))
        px = project(ends_cam, intr)
        # Local scale (px per mm) at the middle, for the clean room across the edge.
        t = (b - a) / np.linalg.norm(b - a)
        nrm = np.array([-t[1], t[0]])
        mid = (a + b) / 2
        step = project(pose.to_camera(np.array([mid, mid + nrm])), intr)
        scale = float(np.linalg.norm(step[1] - step[0]))
        task = EdgeTask(px[0], px[2], seg.clear_left_mm * scale, seg.clear_right_mm * scale,
                        context={"segment": seg, "target": target, "pose": pose, "intrinsics": intr})
        out.append((seg, task, ends_cam[:, 2]))
    return out


def measure(stack: Stack | str | Path, estimator: str = "edge", *,
            progress: Callable[[str, int, int], None] | None = None) -> SampleTable:
    """Measure blur versus distance on every target edge of a stack.

    Parameters
    ----------
    stack : a :class:`~lensfit.stack.Stack` or the path of a stack folder
    estimator : a name from ``lensfit.estimators.ESTIMATORS``
    progress : callable(stage, done, total), optional

    Returns
    -------
    SampleTable

    Raises
    ------
    lensfit.errors.SpecError, lensfit.errors.InputError
        Unreadable or inconsistent input, saturated targets, a setting that cannot be calibrated.
    """
    fn = get_estimator(estimator)
    if not isinstance(stack, Stack):
        stack = load_stack(stack)
    targets = [Target(spec) for spec in stack.targets]
    if not targets:
        raise SpecError(stack.manifest_path, "target", "no [[target]] tables; describe the calibration targets "
                        "(kind, squares, square_mm, ...) so that they can be found")
    n = len(stack.images)
    images: dict[int, np.ndarray] = {}
    detections: dict[int, list[Detection]] = {}
    for i in range(n):
        img = stack.read(i)
        images[i] = img
        found = [d for d in (t.detect(img) for t in targets) if d is not None]
        for d in found:
            _check_saturation(stack, i, img, d)
        detections[i] = found
        if progress:
            progress("detect", i + 1, n)
    table = SampleTable(pixel_pitch_mm=stack.pixel_pitch_mm, image_shape=stack.shape)
    missing = [stack.images[i].file.name for i in range(n) if not detections[i]]
    if missing:
        table.warnings.append(f"no target found in {len(missing)} image(s): {', '.join(missing[:5])}")
    by_setting: dict[str, list[Detection]] = {}
    for i in range(n):
        by_setting.setdefault(stack.images[i].setting, []).extend(detections[i])
    table.intrinsics = calibrate({k: v for k, v in by_setting.items()}, stack.shape)
    by_id = {t.id: t for t in targets}
    for i in range(n):
        entry = stack.images[i]
        intr = table.intrinsics[entry.setting]
        tasks, meta = [], []
        for det in detections[i]:
            pose = estimate_pose(det, intr)
            if pose is None:
                continue
            table.poses[(entry.file.name, det.target_id)] = pose
            for seg, task, z in _edge_tasks(by_id[det.target_id], det, pose, intr):
                tasks.append(task)
                meta.append((det.target_id, seg, z, pose))
        estimates = fn(images[i], tasks) if tasks else []
        for (tid, seg, z, pose), task, est in zip(meta, tasks, estimates):
            flags = list(est.flags)
            if pose.ambiguous:
                flags.append("pose_ambiguous")
            source = "pose"
            if entry.distance_mm is not None:
                z = np.full(3, float(entry.distance_mm))
                source = "manifest"
            table.samples.append(Sample(
                image=entry.file.name, setting=entry.setting, target=tid, edge=seg.id,
                distance_mm=float(z[1]), distance_start_mm=float(z[0]), distance_end_mm=float(z[2]),
                coc_diameter_px=est.coc_diameter_px, sigma_px=est.sigma_px, estimator=estimator,
                flags=";".join(flags), start_px=tuple(float(v) for v in task.start_px),
                end_px=tuple(float(v) for v in task.end_px), distance_source=source))
        images.pop(i)
        if progress:
            progress("measure", i + 1, n)
    return table



