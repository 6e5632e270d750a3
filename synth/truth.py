"""What synth writes beside the images: the ground truth (per-target pose, distance and the CoC
at every edge; per-pixel depth along the chief ray) and stack.toml (what a photographer knows,
never the answer)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


from synth.scene import Scene, Shot
from synth import textures


def chief_ray_depth(shot: Shot, distortion=None) -> np.ndarray:
    """Depth (mm, float64) of the first surface along each pixel centre's chief ray; inf = background.

    With ``distortion`` (``synth.effects.distortion.Distortion``) the chief ray is the one whose
    image the distortion moved to the pixel centre, so the map matches the distorted image.
    """
    cam = shot.camera
    W, H = cam.width_px, cam.height_px
    if distortion is not None:
        from synth.effects.distortion import undistorted_normalised

        dx, dy = undistorted_normalised(W, H, cam.focal_length_px, cam.principal_point_px, distortion)
        x_min, x_max, y_min, y_max = dx.min(axis=0), dx.max(axis=0), dy.min(axis=1), dy.max(axis=1)
    else:
        # Without distortion a direction's x depends on the column alone and its y on the row:
        # full grids as views of one row and one column, never filled in (the demo's 12 shots:
        # 0.32 -> 0.10 s in a fresh process, the same maps on every shipped scene).
        cx, cy = cam.principal_point_px
        u = (np.arange(W) - cx) / cam.focal_length_px
        v = (np.arange(H) - cy) / cam.focal_length_px
        dx, dy = np.broadcast_to(u, (H, W)), np.broadcast_to(v[:, None], (H, W))
        x_min = x_max = u
        y_min = y_max = v
    depth = np.full((H, W), np.inf)
    # Each target is worked out only on the rows and columns its corners' directions span (a
    # plane quad in front of the lens projects inside them): the same values, at a fraction of
    # the cost for a target that fills a part of the frame.
    for obj in shot.objects:
        R, t = obj.pose.R_cam_target, obj.pose.t_cam_target
        w, h = obj.target.size_mm
        corners = t + np.array([[sx * w / 2, sy * h / 2] for sx in (-1, 1) for sy in (-1, 1)]) @ R[:, :2].T
        rows, cols = slice(0, H), slice(0, W)
        if np.all(corners[:, 2] > 0):
            xs, ys = corners[:, 0] / corners[:, 2], corners[:, 1] / corners[:, 2]
            r = np.flatnonzero((y_max >= ys.min()) & (y_min <= ys.max()))
            c = np.flatnonzero((x_max >= xs.min()) & (x_min <= xs.max()))
            if r.size == 0 or c.size == 0:
                continue
            rows, cols = slice(r[0], r[-1] + 1), slice(c[0], c[-1] + 1)
        bx, by, best = dx[rows, cols], dy[rows, cols], depth[rows, cols]
        n = R[:, 2]
        denom = bx * n[0] + by * n[1] + n[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(np.abs(denom) > 1e-15, (t @ n) / denom, np.inf)
        # The hit point in the target's frame, (dx z, dy z, z) - t along its axes, without the
        # (H, W, 3) array: x_local = z (d . R_x) - t . R_x, likewise y.
        on = (z > 0) & (z < best)
        for axis, half in ((0, w / 2), (1, h / 2)):
            a = R[:, axis]
            with np.errstate(invalid="ignore"):
                on &= np.abs(z * (bx * a[0] + by * a[1] + a[2]) - t @ a) <= half
        depth[rows, cols] = np.where(on, z, best)
    return depth


def finite_or_none(x: float):
    return None if not math.isfinite(x) else float(x)


def _distorted_px(px: np.ndarray, cam, distortion) -> np.ndarray:
    """Pinhole pixel positions (..., 2) -> where the distortion shows them."""
    cx, cy = cam.principal_point_px
    f = cam.focal_length_px
    xd, yd = distortion.distort((px[..., 0] - cx) / f, (px[..., 1] - cy) / f)
    return np.stack([cx + f * xd, cy + f * yd], axis=-1)


def target_truth(obj, shot: Shot, distortion=None) -> dict[str, Any]:
    """A target's truth entry. ``*_px`` are pinhole (undistorted) positions; with ``distortion``
    each also has a ``*_px_distorted`` twin: where the image shows it."""
    cam = shot.camera
    pose = obj.pose
    w, h = obj.target.size_mm
    corners = pose.to_camera(np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]]))
    edges = []
    for e in textures.edges(obj.target):
        pts = np.array([e["start_mm"], [(e["start_mm"][0] + e["end_mm"][0]) / 2, (e["start_mm"][1] + e["end_mm"][1]) / 2],
                        e["end_mm"]])
        X = pose.to_camera(pts)
        px = cam.project(X)
        inside = bool(np.all((px[[0, 2], 0] >= 0) & (px[[0, 2], 0] <= cam.width_px - 1)
                             & (px[[0, 2], 1] >= 0) & (px[[0, 2], 1] <= cam.height_px - 1)))
        twin = {}
        if distortion is not None:
            dpx = _distorted_px(px, cam, distortion)
            twin = {"start_px_distorted": dpx[0].tolist(), "end_px_distorted": dpx[2].tolist()}
        edges.append({
            "id": e["id"], "start_mm": [float(v) for v in e["start_mm"]], "end_mm": [float(v) for v in e["end_mm"]],
            "start_px": px[0].tolist(), "end_px": px[2].tolist(), **twin,
            "distance_mm": X[:, 2].tolist(),
            "coc_diameter_px": np.asarray(cam.coc_diameter_px(X[:, 2])).tolist(),
            "in_image": inside,
        })
    entry = {
        "id": obj.target.id,
        "kind": obj.target.target,
        "size_mm": [w, h],
        "distance_mm": float(pose.t_cam_target[2]),
        "coc_diameter_px": float(cam.coc_diameter_px(pose.t_cam_target[2])),
        "pose": {"R_cam_target": pose.R_cam_target.tolist(), "t_cam_target_mm": pose.t_cam_target.tolist()},
        "corners_px": cam.project(corners).tolist(),
        **({"corners_px_distorted": _distorted_px(cam.project(corners), cam, distortion).tolist()}
           if distortion is not None else {}),
        "corners_distance_mm": corners[:, 2].tolist(),
        "edges_sample_points": ["start", "middle", "end"],
        "edges": edges,
    }
    params = {k: (list(v) if isinstance(v, tuple) else v) for k, v in obj.target.params.items() if k != "file"}
    entry["params"] = params
    return entry


def widest_f_number(scene: Scene) -> float | None:
    """A compound lens's full aperture, as its barrel and a camera's EXIF (MaxApertureValue)
    state it: its design's f-number, or the widest the scene opens it to; None for a thin lens or
    a prescription that states no design f-number."""
    from synth.geometry import CompoundLensCamera

    compound = [shot.camera for shot in scene.shots if isinstance(shot.camera, CompoundLensCamera)]
    designed = [c.prescription.design_f_number for c in compound if c.prescription.design_f_number]
    return round(min(designed + [c.f_number for c in compound]), 4) if designed else None


def stack_manifest(scene: Scene, files: list[str], settings: list[str],
                   shown: list[list[str]] | None = None) -> dict[str, Any]:
    """stack.toml: the camera's pixel pitch, the targets' printed geometry, images and labels,
    and (``shown``) which measurement targets each image shows, as a photographer would note."""
    targets = []
    for t in scene.targets:
        if t.target not in ("charuco", "checkerboard", "slanted-edge"):
            continue  # not a measurement target: nothing a photographer would list
        entry: dict[str, Any] = {"id": t.id, "kind": t.target}
        p = t.params
        if t.target in ("charuco", "checkerboard"):
            entry.update(squares=list(p["squares"]), square_mm=p["square_mm"])
        if t.target == "charuco":
            entry.update(marker_mm=p["marker_mm"], dictionary=p["dictionary"])
            if p.get("legacy_pattern"):
                entry["legacy_pattern"] = True
        if t.target == "slanted-edge":
            entry.update(edge_mm=p["edge_mm"])
        targets.append(entry)
    encoding = "srgb" if scene.render.format == "jpeg" else "linear"
    images = [{"file": f, "encoding": encoding, "setting": s} for f, s in zip(files, settings)]
    listed = {t["id"] for t in targets}
    for entry, ids in zip(images, shown or []):
        ids = [i for i in ids if i in listed]
        if ids and len(listed) > 1:  # with one target there is nothing to say
            entry["targets"] = ids
    from synth.geometry import CompoundLensCamera

    out = {"camera": {"pixel_pitch_mm": scene.pixel_pitch_mm}, "target": targets, "image": images}
    # How synth's lens focuses, as its user knows: as a unit (the whole lens moves) unless the
    # scene moves a group inside it.
    internal = any(getattr(shot.camera, "focus_group", None) is not None for shot in scene.shots)
    out["lens"] = {"focusing": "internal" if internal else "unit"}
    if (widest := widest_f_number(scene)) is not None:
        out["lens"]["widest_f_number"] = widest
    if not any(isinstance(shot.camera, CompoundLensCamera) for shot in scene.shots):
        # A thin lens's pupils coincide with it (P = 1), as a user of any renderer's thin-lens camera
        # knows; a compound lens's P is left for the data (or the spread of photographic lenses).
        out["lens"]["pupil_magnification"] = 1.0
        out["lens"]["ideal"] = True  # (no aberrations: its f-number is the blur's own)
    return out
