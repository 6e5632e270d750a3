"""Where a target's edges and corners lie in an image: the edge tasks of a posed target for the
blur estimators, corners refined from the edge lines they measured (``lensfit.measurement.measure``), and a
reading taken into the undistorted image's pixels."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from lensfit.calibration.camera import Intrinsics, TargetPose, estimate_pose, project
from lensfit.estimators.base import EdgeTask, Flag
from lensfit.calibration.targets import Detection, Target


def edge_tasks(target: Target, det: Detection, pose: TargetPose, intr: Intrinsics):
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
                        context={"segment": seg, "target": target, "pose": pose, "intrinsics": intr,
                                 "end_depths_mm": (float(ends_cam[0, 2]), float(ends_cam[2, 2])),
                                 "distortion_scale": distortion_scale(intr, ends_cam[1], ends_cam[2] - ends_cam[0])},
                        border_left_px=seg.border_left_mm * scale, border_right_px=seg.border_right_mm * scale)
        out.append((seg, task, ends_cam[:, 2]))
    return out


#: Step (normalised image coordinates) of the central differences that give the distortion's
#: Jacobian: truncation about 1e-12, rounding about 1e-10 of it.
JACOBIAN_STEP = 1e-6


def distortion_scale(intr: Intrinsics, point_cam: np.ndarray, along_cam: np.ndarray) -> float:
    """The factor by which the lens distortion scales a blur across an edge, at ``point_cam`` (camera
    frame, mm) on an edge running along ``along_cam``: ``|det J| |t| / |J t|``, ``J`` the Jacobian
    of the distortion (distorted image point over undistorted, OpenCV's model as calibrated) and
    ``t`` the edge's direction in the undistorted image; 1 without distortion, NaN where the model
    folds the image (``det J <= 0``: a barrel model far beyond the field it was fitted on).

    Why: a defocused point's rays cross the plane in focus in a disk (the circle of confusion
    carried out into the scene), and the lens images every point of that plane sharply, through
    its distortion. So the spot on the sensor is that disk mapped through the distortion: locally
    ``J`` times the undistorted spot, an ellipse. Across an edge whose image normal is ``n`` the
    ellipse spreads as a uniform disk of ``|J^T n|`` times the diameter (the projection of a
    linearly mapped disk is the disk's, scaled), and ``|J^T n| = |det J| / |J t|`` for ``t`` along
    the edge: the area's scale over the stretch along the edge. Barrel distortion (k1 < 0)
    compresses the image towards the corners, blur included: k1 = -0.25 reads a radial profile
    ``1 + 3 k1 r^2`` as wide, 2-3 % narrower near the demo's corners, and the f-number came out
    0.1 % high over the whole stack."""
    import cv2

    dist = np.asarray(intr.distortion, np.float64)
    if not np.any(dist):
        return 1.0
    x, y, z = (float(v) for v in point_cam)
    dx, dy, dz = (float(v) for v in along_cam)
    u, v = x / z, y / z
    t = np.array([dx * z - x * dz, dy * z - y * dz])  # d(x/z, y/z) along the edge (times z^2)
    h = JACOBIAN_STEP
    pts = np.array([[u + h, v, 1.0], [u - h, v, 1.0], [u, v + h, 1.0], [u, v - h, 1.0]])
    out = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), dist)[0].reshape(4, 2)
    J = np.column_stack([(out[0] - out[1]) / (2 * h), (out[2] - out[3]) / (2 * h)])
    stretch, det = float(np.linalg.norm(J @ t)), float(np.linalg.det(J))
    # det J <= 0: the model folds the image over itself here (beyond where it was fitted): no scale
    g = det * float(np.linalg.norm(t)) / stretch if stretch > 0 and det > 0 else float("nan")
    return g if np.isfinite(g) else float("nan")


#: Points along a target edge at which :func:`unbowed` traces its image through the distortion.
BOW_SAMPLES = 65


def unbowed(line_px, seg, pose: TargetPose, intr: Intrinsics, margin_px: float):
    """The edge line an estimator fitted (``line_px``: its points at the edge's two ends), moved
    so that it passes through the edge's true ends where lens distortion bows the edge's image.

    Distortion images a straight target edge as a curve, and the estimators fit it with a straight
    line (an offset and a turn) over the edge less ``margin_px`` at each end: the least-squares
    line of the curve, which misses the ends, the corners, by most of the bow's depth, towards
    its hollow: with k1 = -0.25 a 150 px edge at 0.2 of the focal length off the axis by 0.035
    and 0.041 px (tests/measurement/test_distortion_blur.py), against corners refined to 0.01-0.02 px. The
    calibration takes such shifts as distortion and focal length. The curve is traced through
    the calibration the edge tasks came from (its distortion and this view's pose,
    :func:`lensfit.calibration.camera.project`), its least-squares line found over the same span, and the
    fitted line moved by that line's offsets at the two ends (0.005 and 0.001 px left in that
    test). On three demo stacks with k1 = -0.25 (the coverage suite's distortion set, seeds 0-2;
    540 refined corners against the truth's poses) the corners' radial error was +0.003, +0.011
    and +0.027 px at 0-0.04, 0.04-0.08 and 0.08-0.12 of the focal length off the axis, growing
    as the distortion does; after, -0.0006, -0.0003 and -0.0006 px (+- 0.001). The calibration had
    taken most of it as distortion: over six such stacks the focal length moved by +0.005 % on
    average (-0.027 -> -0.022 %, sigmas 0.03-0.05 %). Without distortion, the line as fitted."""
    if not np.any(np.asarray(intr.distortion, np.float64)):
        return line_px
    a, b = np.asarray(seg.start_mm, np.float64), np.asarray(seg.end_mm, np.float64)
    u = np.linspace(0.0, 1.0, BOW_SAMPLES)[:, None]
    px = project(pose.to_camera(a + u * (b - a)), intr)
    L = float(np.linalg.norm(px[-1] - px[0]))
    if not L > 0:
        return line_px
    t = (px[-1] - px[0]) / L
    n = np.array([-t[1], t[0]])
    s, bow = (px - px[0]) @ t, (px - px[0]) @ n
    margin = min(margin_px, 0.45 * L)
    keep = (s >= margin) & (s <= L - margin)
    if keep.sum() < 3:
        keep = np.ones_like(s, bool)
    slope, offset = np.polyfit(s[keep], bow[keep], 1)
    if not (np.isfinite(slope) and np.isfinite(offset)):
        return line_px
    q0, q1 = (np.asarray(q, np.float64) for q in line_px)
    along = (q1 - q0) / max(float(np.linalg.norm(q1 - q0)), 1e-12)
    normal = np.array([-along[1], along[0]])
    return (q0 - offset * normal, q1 - (offset + slope * L) * normal)


def bow_margin(task: EdgeTask, est) -> float:
    """The length (px) the edge estimator left out at each end of ``task`` for the reading ``est``:
    its window for the blur it read (:func:`lensfit.estimators.profile.windows`), the whole clean
    room where it read none."""
    from lensfit.estimators.profile import windows

    coc = getattr(est, "coc_diameter_px", None)
    return windows(task, 0.5 * coc if coc else None)[1]


#: 1 sigma (px, each axis) of a corner OpenCV's detector placed and no two edge lines refined:
#: its share in a refined detection's point covariance (refine_corners).
SADDLE_CORNER_SIGMA_PX = 0.1


def refine_corners(det: Detection, target: Target, lines: dict[str, tuple]) -> Detection:
    """Corners as the least-squares intersections of the edge lines through them.

    ``lines`` maps edge ids to ((point, point), CoC diameter in px[, covariance of the line's
    offsets at the two points]) as the estimator found them (``BlurEstimate.line_px``,
    ``line_cov_px2``).

    OpenCV's saddle-point corners carry errors of about 0.1 px on sharp or blurred synthetic
    boards (measured: a 0.4 % focal-length error on a clean stack); the edge lines located by
    the blur estimator are an order of magnitude more precise. A corner keeps its detected
    position unless two lines at least 20 degrees apart pass through it.

    Where every line gives its covariance, the refined detection carries the covariance of its
    points (``point_cov_px2``): a line's error moves every corner on it, and its turn moves the
    corners at its two ends in opposite directions, so neighbouring corners' errors anti-correlate
    (measured on Mitsuba renders: -0.1 to -0.4 between neighbours against the true corners). The
    calibration's residuals then overstate what the focal length is uncertain by, unless read
    through this covariance (:func:`lensfit.calibration.camera.calibrate`).
    """
    through: dict[int, list[tuple[np.ndarray, np.ndarray, int]]] = {}
    reach: dict[int, float] = {}
    line_cov: list[np.ndarray | None] = []
    for seg in target.edges():
        if seg.id not in lines:
            continue
        (p0, p1), coc, *cov = lines[seg.id]
        q0, q1 = np.asarray(p0, float), np.asarray(p1, float)
        t = q1 - q0
        t = t / np.linalg.norm(t)
        for end, cid in enumerate(seg.corner_ids):
            through.setdefault(int(cid), []).append((q0, np.array([-t[1], t[0]]), 2 * len(line_cov) + end))
            reach[int(cid)] = max(reach.get(int(cid), 0.0), coc or 0.0)
        line_cov.append(_psd(cov[0]) if cov and cov[0] is not None else None)
    points = det.image_points_px.copy()
    n = len(det.ids)
    gain = np.zeros((2 * n, 2 * len(line_cov)))  # point errors = gain @ the lines' end offsets
    known = np.zeros(n, bool)  # refined from lines that all state their covariance
    for k, cid in enumerate(det.ids):
        ls = through.get(int(cid), [])
        if len(ls) < 2:
            continue
        normals = np.array([nrm for _, nrm, _ in ls])
        if abs(np.linalg.det(normals.T @ normals)) < np.sin(np.radians(20)) ** 2:
            continue
        A = normals.T @ normals
        b = sum(nrm * (nrm @ q) for q, nrm, _ in ls)
        x = np.linalg.solve(A, b)
        # A refinement, never a jump: blur rounds a thresholded square's corners inward by up to
        # about the blur diameter, saddle-point corners move far less.
        if np.all(np.isfinite(x)) and np.linalg.norm(x - points[k]) < 3.0 + reach.get(int(cid), 0.0):
            points[k] = x
            known[k] = all(line_cov[j // 2] is not None for _, _, j in ls)
            A_inv = np.linalg.inv(A)
            for _, nrm, j in ls:
                gain[2 * k:2 * k + 2, j] = A_inv @ nrm
    point_cov = None
    refined = [k for k in range(n) if np.any(gain[2 * k:2 * k + 2])]
    if refined and all(known[k] for k in refined):
        from scipy.linalg import block_diag

        point_cov = gain @ block_diag(*[np.zeros((2, 2)) if c is None else c for c in line_cov]) @ gain.T
        for k in set(range(n)) - set(refined):
            point_cov[2 * k:2 * k + 2, 2 * k:2 * k + 2] += SADDLE_CORNER_SIGMA_PX**2 * np.eye(2)
    return Detection(det.target_id, det.object_points_mm, points, det.ids, point_cov)


def _psd(cov: tuple[float, float, float]) -> np.ndarray | None:
    """A line's (variance, covariance, variance) as a positive semi-definite 2 x 2, or None."""
    m = np.array([[cov[0], cov[1]], [cov[1], cov[2]]], np.float64)
    if not np.all(np.isfinite(m)):
        return None
    w, v = np.linalg.eigh(m)
    return (v * np.maximum(w, 0.0)) @ v.T


#: The distortion scales (lensfit.measurement.edge_geometry.distortion_scale) a blur reading is taken through:
#: beyond them the calibrated model is folding or far outside what it was fitted on.
DISTORTION_SCALE_RANGE = (0.2, 5.0)


#: Targets whose corners are saddle points, which a monotone tone curve leaves in place: only
#: their lines through the corners say where a lens drew the edges (a slanted square's convex
#: corners read off them, and its edges 0.3 of a radius from those lines in linear renders).
SADDLE_KINDS = ("charuco", "checkerboard")


def tone_shift(first: dict[int, tuple[list, list, list]], by_id: dict[str, Target]) -> float:
    """How far a tone curve moved the first pass's edges toward their bright side, in blur radii:
    their pooled offset from the lines through the target's corners where it names a tone
    mismatch (``lensfit.measurement.processing``), else 0; over the edges of ``SADDLE_KINDS``
    targets alone (``by_id``: the targets by id). (A curve the declared encoding does not
    undo moves every edge toward one side, by a share of its blur; a corner where an unequal
    number or blur of edges meets, as on a board's rim or a tilted board, moves with them, and the
    calibrated focal length with the corners: +0.75 % through darktable's default at f/5.6.)"""
    from lensfit.measurement.processing import offset_significant, pooled_offset

    offset, sigma, edges = pooled_offset((bright_offset(est, task), est.coc_diameter_px)
                                         for tasks, meta, estimates in first.values()
                                         for task, (tid, *_), est in zip(tasks, meta, estimates)
                                         if by_id[tid].kind in SADDLE_KINDS)
    return offset if offset_significant(offset, sigma, edges) else 0.0


def tone_shifts(first: dict[int, tuple[list, list, list]], encodings: list[str],
                by_id: dict[str, Target]) -> dict[int, float]:
    """:func:`tone_shift` per image of ``first``, pooled over the images of one declared encoding
    (``encodings``, by image): a RAW file beside its camera's JPEG has no tone curve. Images
    declared linear keep their lines (a linear file with a curve left in has its f-number refused
    anyway)."""
    groups: dict[str, dict[int, tuple]] = {}
    for i, passed in first.items():
        groups.setdefault(encodings[i], {})[i] = passed
    out: dict[int, float] = {}
    for encoding, group in groups.items():
        out.update(dict.fromkeys(group, 0.0 if encoding == "linear" else tone_shift(group, by_id)))
    return out


def refined_detections(detections: list[Detection], first: tuple[list, list, list], intr, by_id: dict[str, Target],
             fresh_poses: bool = False, shift_radii: float = 0.0) -> list[Detection]:
    """An image's detections with their corners refined from the edge lines of the first pass
    (``first``: its tasks, their (target, segment, depths, pose) and the readings), each line
    moved through its edge's true ends where ``intr``'s distortion bows the edge
    (:func:`lensfit.measurement.edge_geometry.unbowed`), through the pose the edge was measured with or, with
    ``fresh_poses``, the detection's pose under ``intr``; and back by ``shift_radii`` of its blur
    radius from its bright side (:func:`tone_shift`)."""
    tasks, meta, estimates = first
    out = []
    for det in detections:
        pose_now = estimate_pose(det, intr) if fresh_poses else None
        lines = {seg.id: (unbowed(_shifted(est, shift_radii), seg, pose if pose_now is None else pose_now, intr,
                                  bow_margin(task, est)),
                          est.coc_diameter_px, est.line_cov_px2)
                 for task, (tid, seg, _, pose), est in zip(tasks, meta, estimates)
                 if tid == det.target_id and est.line_px is not None}
        out.append(refine_corners(det, by_id[det.target_id], lines))
    return out


def _shifted(est: Any, shift_radii: float) -> Any:
    """``est.line_px`` moved by ``shift_radii`` of the blur radius away from the edge's bright side."""
    if not shift_radii or est.bright_side is None or est.coc_diameter_px is None:
        return est.line_px
    step = -shift_radii * 0.5 * est.coc_diameter_px * np.asarray(est.bright_side, np.float64)
    return tuple(np.asarray(p, np.float64) + step for p in est.line_px)


def undistorted_blur(est: Any, scale: float, flags: list[Flag]) -> Any:
    """An edge's blur reading in the undistorted image's pixels, where the CoC model lives: the
    image's reading over the distortion's ``scale`` across the edge (its sigma and the uniform
    disk's reading with it; flag ``distortion_scaled``); none where the scale is out of
    ``DISTORTION_SCALE_RANGE`` (flag ``distortion_extreme``). ``flags`` is extended in place."""
    if scale == 1.0 or est.coc_diameter_px is None:
        return est
    if not (math.isfinite(scale) and DISTORTION_SCALE_RANGE[0] <= scale <= DISTORTION_SCALE_RANGE[1]):
        flags.append(Flag.DISTORTION_EXTREME)
        return dataclasses.replace(est, coc_diameter_px=None, sigma_px=None)
    flags.append(Flag.DISTORTION_SCALED)

    def over(v):
        return None if v is None else v / scale

    return dataclasses.replace(est, coc_diameter_px=over(est.coc_diameter_px), sigma_px=over(est.sigma_px),
                               disk_diameter_px=over(est.disk_diameter_px), disk_sigma_px=over(est.disk_sigma_px))


def bright_offset(est: Any, task: EdgeTask) -> float | None:
    """How far the edge ``est`` read lies from ``task``'s line (through the target's corners),
    toward the edge's bright side, px (None where the estimator locates no line)."""
    if est.line_px is None or est.bright_side is None:
        return None
    middle = 0.5 * (np.asarray(est.line_px[0], np.float64) + np.asarray(est.line_px[1], np.float64))
    along = 0.5 * (np.asarray(task.start_px, np.float64) + np.asarray(task.end_px, np.float64))
    return float(np.dot(middle - along, np.asarray(est.bright_side, np.float64)))
