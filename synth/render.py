"""The render pipeline: scene -> per-shot method choice -> stages -> images and ground truth.

``render(scene)`` returns everything in memory (images, per-pixel truth maps, truth.json and
stack.toml contents); ``synth.stack.write_stack`` writes it. Stages are listed per shot by
``plan(scene)``: the geometric render (the ``defocus`` effect, by the chosen method) and
whatever effects the scene lists after it. An effect that is not listed has no stage: it costs
nothing and changes nothing.
"""

from __future__ import annotations

import math
import sys
import types
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit import __version__
from lensfit.errors import InputError
from lensfit.limits import RENDER_MEMORY_BYTES, format_bytes
from synth.convolve import blurred_footprint_px, convolve_bytes, render_convolve
from synth.raytrace import BYTES_PER_SAMPLE, raytrace_bytes, render_raytrace
from synth.effects import Effects
from synth.scene import Scene, Shot, load_scene
from synth import textures

METHODS = ("auto", "raytrace", "convolve")

#: Rough throughputs on a 2-core machine, used only for the cost estimates of ``synth plan``.
RAYTRACE_SAMPLES_PER_S = 150e6  # synth bench: ~165 M/s once compiled
CONVOLVE_SUBPIXELS_PER_S = 25e6


@dataclass(frozen=True)
class ShotPlan:
    """What rendering one shot involves: its method, its stages in order and their costs.

    ``stages`` names each stage (with its key parameter); ``stage_seconds`` estimates each on
    2 cores after compilation; ``estimated_s`` is their sum.
    """

    shot: Shot
    method: str
    exact: bool
    reason: str
    stages: tuple[str, ...]
    estimated_s: float
    work: str
    stage_seconds: tuple[float, ...] = ()


def _overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


#: Below this CoC diameter (px) the sub-pixel convolution's error near sharp edges exceeds
#: about 2e-3 of the contrast (tests/test_synth_render.py), so ``auto`` ray traces instead.
CONVOLVE_MIN_COC_PX = 2.0


def convolve_is_exact(shot: Shot) -> tuple[bool, str]:
    """Whether ``convolve`` renders this shot exactly, and why (or why not)."""
    tilted = [o.target.id for o in shot.objects if not o.pose.fronto_parallel]
    if tilted:
        return False, f"tilted target(s) {', '.join(tilted)}: blur varies across the plane"
    small = [o.target.id for o in shot.objects
             if float(shot.camera.coc_diameter_px(o.pose.t_cam_target[2])) < CONVOLVE_MIN_COC_PX]
    if small:
        return False, (f"target(s) {', '.join(small)} blurred by less than {CONVOLVE_MIN_COC_PX:g} px: sub-pixel "
                       "convolution is not exact there")
    boxes = [(o.target.id, blurred_footprint_px(o, shot)) for o in shot.objects]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            if _overlap(boxes[i][1], boxes[j][1]):
                return False, (f"blurred images of {boxes[i][0]} and {boxes[j][0]} overlap: partial occlusion "
                               "needs ray tracing")
    return True, "all targets fronto-parallel, no overlapping blur: convolution with the exact PSF is exact"


def _estimate(shot: Shot, method: str, spp: int, supersampling: int) -> tuple[float, str]:
    cam = shot.camera
    if method == "raytrace":
        samples = cam.width_px * cam.height_px * spp
        return samples / RAYTRACE_SAMPLES_PER_S * max(1, len(shot.objects)) ** 0.5, f"{samples / 1e6:.0f} M lens samples"
    sub = 0.0
    for o in shot.objects:
        u0, v0, u1, v1 = blurred_footprint_px(o, shot)
        w = max(0.0, min(u1, cam.width_px) - max(u0, 0))
        h = max(0.0, min(v1, cam.height_px) - max(v0, 0))
        sub += w * h * supersampling**2
    return sub / CONVOLVE_SUBPIXELS_PER_S + 0.05, f"{sub / 1e6:.1f} M sub-pixels convolved"


def choose_method(shot: Shot, requested: str, effects: Effects | None = None, *, samples_per_pixel: int = 1,
                  supersampling: int = 4) -> tuple[str, bool, str]:
    """(method, exact, reason) for one shot. ``auto`` picks the cheapest exact method that fits
    the memory budget (``lensfit.limits.RENDER_MEMORY_BYTES``); a method that does not fit is
    refused before anything is allocated."""
    if requested not in METHODS:
        raise InputError("method", requested, "one of " + ", ".join(METHODS))
    method, exact, why = _choose(shot, requested, effects, supersampling)
    _check_memory(shot, method, samples_per_pixel, supersampling, effects)
    return method, exact, why


def _choose(shot: Shot, requested: str, effects: Effects | None, supersampling: int) -> tuple[str, bool, str]:
    only_raytrace = effects.needs_raytrace if effects is not None else None
    if getattr(shot.camera, "prescription", None) is not None:
        only_raytrace = f"the compound lens {shot.camera.prescription.name}"
    if only_raytrace:
        if requested == "convolve":
            raise InputError("method", requested, "raytrace or auto", f"{only_raytrace} is simulated only by ray tracing")
        return "raytrace", True, f"{requested}: {only_raytrace} needs ray tracing"
    exact, why = convolve_is_exact(shot)
    if requested == "raytrace":
        return "raytrace", True, "requested; ray tracing is exact for every planar scene"
    if requested == "convolve":
        return "convolve", exact, ("requested; " + why) if exact else f"requested although not exact: {why}"
    if exact and convolve_bytes(shot, supersampling) > RENDER_MEMORY_BYTES:
        return "raytrace", True, (f"auto: {why}, but its blur kernel and FFT would need "
                                  f"{format_bytes(convolve_bytes(shot, supersampling))}: ray tracing instead")
    if exact:
        return "convolve", True, "auto: " + why
    return "raytrace", True, "auto: " + why


#: Bytes per pixel and channel that a shot's images take through the pipeline (float32 render,
#: float64 stages, sensor values) and its truth maps (depth and CoC, float32), measured loosely.
IMAGE_BYTES_PER_PIXEL = 32


def _check_memory(shot: Shot, method: str, spp: int, supersampling: int, effects: Effects | None) -> None:
    """Refuse a shot whose render would take more than the memory budget, naming the option."""
    budget = format_bytes(RENDER_MEMORY_BYTES)
    cam = shot.camera
    channels = effects.channels if effects is not None else 1
    images = float(IMAGE_BYTES_PER_PIXEL) * cam.width_px * cam.height_px * (channels + 1)
    if images > RENDER_MEMORY_BYTES:
        raise InputError("camera.width_px", cam.width_px, f"a smaller image than {cam.width_px} x {cam.height_px} px",
                         f"its images would need {format_bytes(images)} in the pipeline (budget {budget})")
    if effects is not None and effects.diffraction is not None:
        from synth.effects import diffraction

        need = diffraction.bytes_needed(effects.diffraction, working_f_number(cam), cam.pixel_pitch_mm,
                                        cam.width_px, cam.height_px)
        if need > RENDER_MEMORY_BYTES:
            raise InputError("diffraction", f"f/{working_f_number(cam):.3g} at {cam.pixel_pitch_mm * 1000:g} um pixels",
                             "an Airy pattern a few hundred pixels wide or less",
                             f"its kernel and FFT would need {format_bytes(need)} (budget {budget}); use a larger "
                             "pixel pitch or a smaller f-number")
    if method == "raytrace":
        need = raytrace_bytes(shot.camera.width_px, spp)
        if need > RENDER_MEMORY_BYTES:
            most = int(RENDER_MEMORY_BYTES // (BYTES_PER_SAMPLE * shot.camera.width_px))
            raise InputError("samples_per_pixel", spp, f"at most {most} for a {shot.camera.width_px} px wide image",
                             f"one image row of ray-tracing samples would need {format_bytes(need)} (budget {budget})")
    else:
        need = convolve_bytes(shot, supersampling)
        if need > RENDER_MEMORY_BYTES:
            raise InputError("method", "convolve", "raytrace or auto for this shot",
                             f"{shot.name}'s blur kernel and FFT grid would need {format_bytes(need)} (budget "
                             f"{budget}): its blur ({shot.camera.coc_diameter_px(min(o.pose.t_cam_target[2] for o in shot.objects)):.3g} "
                             "px or more) is too large to convolve; is the focus distance meant to be so close to the "
                             "focal length?")


def _stages(scene: Scene, shot: Shot, method: str, geometric_s: float) -> list[tuple[str, float]]:
    """(stage, estimated seconds) in pipeline order; only the effects the scene calls for."""
    from synth.effects import diffraction, exposure, noise

    fx, cam = scene.effects, shot.camera
    W, H, C = cam.width_px, cam.height_px, fx.channels
    pixels = W * H
    ca = fx.chromatic_aberration
    renders = 3 if ca is not None and ca.longitudinal else 1  # channels the lens treats alike share a render
    waves = getattr(cam, "wavelengths_nm", ())
    if waves:
        renders = len(waves)
        detail = f", x{renders} wavelengths {'/'.join(f'{w:g}' for w in waves)} nm -> {'RGB' if C == 3 else 'grey'}"
    else:
        detail = ", x3 channels" if renders == 3 else ""
    out = [(f"defocus ({method}{detail})", geometric_s * renders)]
    if "aperture" in fx.names:
        a = fx.aperture
        detail = {"polygon": f"{a.blades} blades, {a.rotation_deg:g} deg", "anamorphic": f"squeeze {a.squeeze:g}",
                  "circle": "circle"}[a.shape]
        out.append((f"aperture ({detail}, in the {method} stage)", 0.0))
    if fx.diffraction is not None:
        waves = "/".join(f"{w:g}" for w in fx.diffraction.wavelength_nm)
        out.append((f"diffraction (Airy, {waves} nm)", diffraction.seconds(W, H, C)))
    if fx.vignetting is not None:
        v = fx.vignetting
        parts = (["cos^4"] if v.natural else []) + (["front stop in the ray tracer"] if v.optical else [])
        out.append((f"vignetting ({', '.join(parts) or 'none'})", 5e-9 * pixels * C if v.natural else 0.0))
    lateral = fx.chromatic_aberration is not None and fx.chromatic_aberration.lateral
    if fx.distortion is not None and method == "raytrace":
        out.append(("distortion (exact, in the ray tracer)", 4e-7 * pixels))
    if lateral or (fx.distortion is not None and method != "raytrace"):
        name = "lateral CA" if method == "raytrace" or fx.distortion is None else (
            "distortion" + (" + lateral CA" if lateral else ""))
        out.append((f"{name} (cubic resampling)", 1.5e-7 * pixels * C
                    + (4e-7 * pixels if fx.distortion is not None and method != "raytrace" else 0.0)))
    if fx.chromatic_aberration is not None and fx.chromatic_aberration.longitudinal:
        out.append(("chromatic_aberration (longitudinal: per-channel focus, in the defocus stage)", 0.0))
    if fx.exposure is not None:
        e = fx.exposure.for_shot(shot.shutter_s, shot.iso)
        iso = e.iso if e.iso is not None else fx.sensor.base_iso
        out.append((f"exposure ({e.shutter_s:g} s, ISO {iso:g}, {fx.sensor.name})", exposure.seconds(W, H)))
    if fx.mosaic is not None:
        out.append((f"mosaic ({fx.mosaic.pattern})", 1e-8 * pixels))
    if fx.noise is not None:
        out.append(("noise (shot + read)", noise.seconds(W, H)))
    if fx.exposure is not None:
        out.append((f"readout ({fx.sensor.bit_depth}-bit DN)", 5e-9 * pixels))
    else:
        out.append(("quantise (16-bit)" if scene.render.format != "float-tiff" else "store (float32)", 1e-8 * pixels * C))
    return out


def plan(scene: Scene) -> list[ShotPlan]:
    """The stages each shot will run, its method and an estimated cost."""
    out = []
    r = scene.render
    for shot in scene.shots:
        method, exact, reason = choose_method(shot, r.method, scene.effects, samples_per_pixel=r.samples_per_pixel,
                                              supersampling=r.supersampling)
        seconds, work = _estimate(shot, method, r.samples_per_pixel, r.supersampling)
        stages = _stages(scene, shot, method, seconds)
        out.append(ShotPlan(shot, method, exact, reason, tuple(n for n, _ in stages), sum(t for _, t in stages), work,
                            tuple(t for _, t in stages)))
    return out


# --------------------------------------------------------------------------- ground truth


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
    else:
        cx, cy = cam.principal_point_px
        u = (np.arange(W) - cx) / cam.focal_length_px
        v = (np.arange(H) - cy) / cam.focal_length_px
        dx, dy = np.meshgrid(u, v)
    depth = np.full((H, W), np.inf)
    for obj in shot.objects:
        R, t = obj.pose.R_cam_target, obj.pose.t_cam_target
        n = R[:, 2]
        denom = dx * n[0] + dy * n[1] + n[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(np.abs(denom) > 1e-15, (t @ n) / denom, np.inf)
        hit = np.stack([dx * z, dy * z, z], axis=-1) - t
        x_local, y_local = hit @ R[:, 0], hit @ R[:, 1]
        w, h = obj.target.size_mm
        on = (z > 0) & (np.abs(x_local) <= w / 2) & (np.abs(y_local) <= h / 2) & (z < depth)
        depth = np.where(on, z, depth)
    return depth


def _finite_or_none(x: float):
    return None if not math.isfinite(x) else float(x)


def _distorted_px(px: np.ndarray, cam, distortion) -> np.ndarray:
    """Pinhole pixel positions (..., 2) -> where the distortion shows them."""
    cx, cy = cam.principal_point_px
    f = cam.focal_length_px
    xd, yd = distortion.distort((px[..., 0] - cx) / f, (px[..., 1] - cy) / f)
    return np.stack([cx + f * xd, cy + f * yd], axis=-1)


def _target_truth(obj, shot: Shot, distortion=None) -> dict[str, Any]:
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


#: Image file formats synth writes: 16-bit linear PNG/TIFF, float32 TIFF, DNG (Bayer mosaic, raw
#: DN) and JPEG (8-bit sRGB, as a camera's JPEG; quality ``render.jpeg_quality``).
IMAGE_FORMATS = ("png", "tiff", "float-tiff", "dng", "jpeg")


@dataclass
class RenderResult:
    """Everything a stack holds, in memory.

    Attributes
    ----------
    images : dict of file name -> float32 (H, W) linear radiance (before quantisation)
    maps : dict of file name -> {"depth_mm": float32 (H, W), "coc_diameter_px": float32 (H, W)}
    truth : the truth.json object
    manifest : the stack.toml object (only what a photographer would know)
    image_format : one of ``IMAGE_FORMATS`` (how ``synth.stack.write_stack`` stores images)
    raw : dict of file name -> uint16 (H, W) sensor values (DN), for scenes with ``exposure`` or
        ``mosaic``: what the files hold (``images`` keeps the linear radiance before the sensor)
    levels : dict of file name -> {"black_level", "white_level"} of the raw values
    exif : dict of file name -> what a camera records (focal length, f-number, focus distance,
        pixel pitch, exposure time and ISO); DNG and JPEG files carry it as EXIF
    stage_seconds : dict of file name -> {stage: wall seconds} as measured in this render
        (kept out of truth.json, which stays reproducible)
    """

    images: dict[str, np.ndarray] = field(default_factory=dict)
    maps: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    truth: dict[str, Any] = field(default_factory=dict)
    manifest: dict[str, Any] = field(default_factory=dict)
    image_format: str = "png"
    jpeg_quality: int = 95
    raw: dict[str, np.ndarray] = field(default_factory=dict)
    levels: dict[str, dict[str, int]] = field(default_factory=dict)
    exif: dict[str, dict[str, float]] = field(default_factory=dict)
    stage_seconds: dict[str, dict[str, float]] = field(default_factory=dict)


def quantise_16bit(image: np.ndarray) -> np.ndarray:
    """Linear radiance -> uint16: round(65535 * clip(v, 0, 1))."""
    return np.round(np.clip(image, 0.0, 1.0) * 65535.0).astype(np.uint16)


def _shot_seed(seed: int, k: int) -> int:
    return (seed * 1_000_003 + k * 7_919) % (1 << 32)


def image_extension(fmt: str) -> str:
    return {"png": ".png", "dng": ".dng", "jpeg": ".jpg"}.get(fmt, ".tiff")


def working_f_number(camera) -> float:
    """Image-side f-number s/A (N at infinity focus; 2N at 1:1)."""
    return camera.sensor_distance_mm / camera.aperture_diameter_mm


def render_shot(scene: Scene, sp: ShotPlan, k: int, tick: Callable[[int], None]):
    """One shot through its stages: (linear radiance float32 (H, W) or (H, W, 3), raw DN uint16
    or None, per-image truth entries, seconds per stage). Only the stages the scene calls for run."""
    r, fx, shot = scene.render, scene.effects, sp.shot
    seconds: dict[str, float] = {}
    last = [time.perf_counter()]

    def lap(stage: str) -> None:
        now = time.perf_counter()
        seconds[stage] = seconds.get(stage, 0.0) + now - last[0]
        last[0] = now

    cam = shot.camera
    extra: dict[str, Any] = {}
    ca = fx.chromatic_aberration
    waves = getattr(cam, "wavelengths_nm", ())
    if waves:  # one render per wavelength, mixed into grey or colour below (synth.spectral)
        cameras = cam.spectral_cameras()
    else:
        cameras = ca.channel_cameras(cam) if ca is not None and ca.longitudinal else [cam] * fx.channels
    stop = fx.vignetting.front_stop() if fx.vignetting is not None else None
    kwargs_rt = {}
    if fx.aperture.shape != "circle":
        kwargs_rt["aperture"] = fx.aperture.static
    if stop is not None:
        kwargs_rt["front_stop"] = stop
    exact_distortion = fx.distortion is not None and sp.method == "raytrace"
    if exact_distortion:
        from synth.effects.distortion import pixel_warp

        kwargs_rt["warp"] = pixel_warp(cam, fx.distortion)
    planes: list[np.ndarray] = []
    distinct = len({id(c) for c in cameras})
    for c, ccam in enumerate(cameras):
        same = next((j for j in range(c) if cameras[j] is ccam), None)
        if same is not None:  # a channel the lens treats like an earlier one: no second render
            planes.append(planes[same])
            continue
        rows = (lambda n, _d=distinct: tick(n / _d)) if distinct > 1 else tick
        cam_kw = {} if ccam is cam else {"camera": ccam}
        if sp.method == "raytrace":
            img = render_raytrace(shot, scene.background_value, r.samples_per_pixel, _shot_seed(r.seed, k), rows,
                                  **cam_kw, **kwargs_rt)
        else:
            img = render_convolve(shot, scene.background_value, r.supersampling, **cam_kw,
                                  **({"aperture": fx.aperture} if fx.aperture.shape != "circle" else {}))
            rows(cam.height_px)
        planes.append(img)
    if waves:
        from synth.spectral import combine

        image = combine(planes, waves, fx.channels)
    else:
        image = planes[0] if len(planes) == 1 else np.stack(planes, axis=-1)
    lap("defocus")
    if fx.diffraction is not None:
        from synth.effects import diffraction

        Nw = working_f_number(cam)
        image = diffraction.apply(image, fx.diffraction, Nw, cam.pixel_pitch_mm).astype(np.float32)
        extra["diffraction"] = fx.diffraction.truth(Nw, cam.pixel_pitch_mm)
        lap("diffraction")
    if fx.vignetting is not None and fx.vignetting.natural:
        from synth.effects import vignetting

        image = vignetting.apply_natural(image, cam)
        lap("vignetting")
    lateral = ca is not None and ca.lateral
    if (fx.distortion is not None and not exact_distortion) or lateral:
        from synth.effects import distortion

        image = distortion.warp(image, cam, None if exact_distortion else fx.distortion,
                                ca.magnification if lateral else None)
        lap("distortion")
    if fx.distortion is not None:
        extra["distortion"] = {**fx.distortion.truth(cam.focal_length_px, cam.principal_point_px),
                               "applied": ("in the ray tracer (each sample's own undistorted ray)" if exact_distortion
                                           else "cubic resampling of the rendered image")}
    if ca is not None:
        extra["chromatic_aberration"] = ca.truth(cam)
    raw = None
    if fx.exposure is not None:
        from synth.effects import exposure, noise

        e = fx.exposure.for_shot(shot.shutter_s, shot.iso)
        iso = e.iso if e.iso is not None else fx.sensor.base_iso
        Nw = working_f_number(cam)
        signal = exposure.mean_electrons(image, e, fx.sensor, Nw, fx.aperture.area_fraction)
        lap("exposure")
        if fx.mosaic is not None:
            from synth.effects import mosaic

            signal = mosaic.apply(signal, fx.mosaic)
            lap("mosaic")
        read = None
        if fx.noise is not None:
            signal, read = noise.draw(signal, fx.noise, fx.sensor.read_noise_e, noise.generator(r.seed, k))
            lap("noise")
        raw = exposure.readout(signal, fx.sensor, iso, read)
        extra["exposure"] = exposure.truth(e, fx.sensor, Nw, fx.aperture.area_fraction)
        lap("readout")
    elif fx.mosaic is not None:
        from synth.effects import mosaic

        raw = quantise_16bit(mosaic.apply(image, fx.mosaic))
        lap("mosaic")
    return image, raw, extra, seconds


def check_overrides(*, samples_per_pixel: int | None = None, supersampling: int | None = None,
                    seed: int | None = None) -> None:
    """The ranges of the scene spec's [render] fields, for values given as arguments."""
    if samples_per_pixel is not None and not 1 <= samples_per_pixel <= 65536:
        raise InputError("samples_per_pixel", samples_per_pixel, "between 1 and 65536")
    if supersampling is not None and not 1 <= supersampling <= 16:
        raise InputError("supersampling", supersampling, "between 1 and 16")
    if seed is not None and not 0 <= seed < 2**32:
        raise InputError("seed", seed, "between 0 and 2**32 - 1")


def render(scene: Scene | str | Path, *, method: str | None = None, samples_per_pixel: int | None = None,
           seed: int | None = None, supersampling: int | None = None, image_format: str | None = None,
           progress: Callable[[str, int, int], None] | None = None) -> RenderResult:
    """Render every shot of a scene; deterministic for a seed.

    Parameters
    ----------
    scene : Scene or path to a scene TOML file.
    method, samples_per_pixel, seed, supersampling, image_format : optional overrides of ``[render]``
        (``image_format`` overrides ``render.format``: one of ``IMAGE_FORMATS``).
    progress : callable(shot_name, done_rows, total_rows), optional; called as rows finish.

    Returns
    -------
    RenderResult
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    check_overrides(samples_per_pixel=samples_per_pixel, supersampling=supersampling, seed=seed)
    if image_format is not None and image_format not in IMAGE_FORMATS:
        raise InputError("image_format", image_format, "one of " + ", ".join(IMAGE_FORMATS))
    problem = scene.effects.format_problem(image_format) if image_format is not None else None
    if problem is not None:
        raise InputError("image_format", image_format, *problem)
    scene = scene.with_render(method=method, samples_per_pixel=samples_per_pixel, seed=seed,
                              supersampling=supersampling, format=image_format)
    r = scene.render
    result = RenderResult(image_format=r.format, jpeg_quality=r.jpeg_quality)
    images_truth, settings = [], {}
    methods_used = set()
    plans = plan(scene)
    for k, sp in enumerate(plans):
        shot, cam = sp.shot, sp.shot.camera
        name = shot.name + image_extension(r.format)
        done = [0]

        def tick(n, _name=shot.name, _h=cam.height_px):
            done[0] += n
            if progress is not None:
                progress(_name, done[0], _h)

        img, raw, extra, seconds = render_shot(scene, sp, k, tick)
        result.stage_seconds[name] = seconds
        methods_used.add(sp.method)
        result.images[name] = img
        if raw is not None:
            result.raw[name] = raw
            sensor = scene.effects.sensor
            result.levels[name] = ({"black_level": sensor.black_level_dn, "white_level": sensor.white_level_dn}
                                   if sensor is not None else {"black_level": 0, "white_level": 65535})
        # What a camera writes into its files (DNG and JPEG carry it as EXIF): nominal values, as
        # a camera reports them (focus distance in whole centimetres, as Canon's maker notes do).
        result.exif[name] = {"focal_length_mm": cam.focal_length_mm, "f_number": cam.f_number,
                             "pixel_pitch_mm": cam.pixel_pitch_mm, "width_px": cam.width_px,
                             **({"focus_distance_mm": round(cam.focus_distance_mm, -1)}
                                if math.isfinite(cam.focus_distance_mm) else {}),
                             **({"shutter_s": extra["exposure"]["shutter_s"], "iso": extra["exposure"]["iso"]}
                                if "exposure" in extra else {})}
        depth = chief_ray_depth(shot, scene.effects.distortion)
        coc = np.asarray(cam.coc_diameter_px(depth))
        map_file = f"truth/{shot.name}_maps.npz"
        result.maps[map_file] = {"depth_mm": depth.astype(np.float32), "coc_diameter_px": coc.astype(np.float32)}
        settings.setdefault(shot.setting, {
            "f_number": cam.f_number,
            "focus_distance_mm": _finite_or_none(cam.focus_distance_mm),
            "inverse_focus_distance_per_mm": cam.inverse_focus_distance,
            "sensor_distance_mm": cam.sensor_distance_mm,
            "focus_distance_from_sensor_mm": _finite_or_none(cam.focus_distance_mm + cam.sensor_distance_mm),
            "aperture_diameter_mm": cam.aperture_diameter_mm,
            "focal_length_px": cam.focal_length_px,
            **(cam.truth() if getattr(cam, "prescription", None) is not None else {}),
        })
        images_truth.append({
            "file": name, "shot": shot.name, "setting": shot.setting,
            "method": sp.method, "method_exact": sp.exact, "method_reason": sp.reason,
            "samples_per_pixel": r.samples_per_pixel if sp.method == "raytrace" else None,
            "supersampling": r.supersampling if sp.method == "convolve" else None,
            "seed": _shot_seed(r.seed, k) if sp.method == "raytrace" else None,
            "stages": list(sp.stages),
            **extra,
            "maps": map_file,
            "targets": [_target_truth(o, shot, scene.effects.distortion) for o in shot.objects],
        })
    cx, cy = scene.shots[0].camera.principal_point_px
    result.truth = {
        "scene": scene.name,
        "focal_length_mm": scene.focal_length_mm,
        "pixel_pitch_mm": scene.pixel_pitch_mm,
        "width_px": scene.width_px,
        "height_px": scene.height_px,
        "principal_point_px": [cx, cy],
        "aperture": scene.aperture,
        "background_value": scene.background_value,
        "settings": settings,
        "images": images_truth,
        "effects": list(r.effects),
        "effect_parameters": scene.effects.truth(),
        "method": methods_used.pop() if len(methods_used) == 1 else "mixed",
        "method_requested": r.method,
        "samples_per_pixel": r.samples_per_pixel,
        "supersampling": r.supersampling,
        "seed": r.seed,
        "intensity": "linear radiance; 16-bit files hold round(65535 * clip(value, 0, 1))",
        "conventions": "data_specs/CONVENTIONS.md",
        "version": __version__,
    }
    result.manifest = stack_manifest(scene, [i["file"] for i in images_truth], [i["setting"] for i in images_truth],
                                     [[o.target.id for o in sp.shot.objects] for sp in plans])
    if r.format not in ("dng", "jpeg"):  # JPEGs hold the levels applied
        for entry in result.manifest["image"]:
            entry.update(result.levels.get(entry["file"], {}))
    return result


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
    return {"camera": {"pixel_pitch_mm": scene.pixel_pitch_mm}, "target": targets, "image": images}


class _CallableModule(types.ModuleType):
    """``synth.render`` names both this module and its main function: once the module is imported
    the package attribute is the module, so calling it renders (``synth.render(scene, ...)``)."""

    def __call__(self, scene, **kwargs) -> RenderResult:
        return render(scene, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
