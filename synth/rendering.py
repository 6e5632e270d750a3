"""The render pipeline: scene -> per-shot method choice (``synth.planning``) -> stages -> images,
and the ground truth (``synth.truth``).

``render(scene)`` returns everything in memory (images, per-pixel truth maps, truth.json and
stack.toml contents); ``synth.stack.write_stack`` writes it. Stages are listed per shot by
``plan(scene)``: the geometric render (the ``defocus`` effect, by the chosen method) and
whatever effects the scene lists after it. An effect that is not listed has no stage: it costs
nothing and changes nothing.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit import __version__
from lensfit.errors import InputError
from lensfit.outputs.writers import provenance
from synth.convolve import block_mean
from synth.mitsuba import VARIANTS as MITSUBA_VARIANTS
from synth.methods import REGISTRY, RenderJob
from synth.raytrace import cell_factor
from synth.scene import Scene, load_scene
from synth.seeds import raytrace_seed
from synth.effects.stages import ShotState, fine_choice, quantise_16bit, run_stages, working_f_number
from synth.planning import METHODS, ShotPlan, choose_method, convolve_is_exact, plan
from synth.truth import finite_or_none, target_truth, chief_ray_depth, stack_manifest, widest_f_number

#: Planning and truth live in synth.planning and synth.truth; their public names are here too.
__all__ = ["render", "plan", "GeometricCache", "choose_method", "convolve_is_exact", "check_overrides", "RenderResult",
           "ShotPlan",
           "METHODS", "IMAGE_FORMATS", "image_extension", "quantise_16bit", "working_f_number", "chief_ray_depth",
           "stack_manifest"]


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


def image_extension(fmt: str) -> str:
    return {"png": ".png", "dng": ".dng", "jpeg": ".jpg"}.get(fmt, ".tiff")


class GeometricCache:
    """The geometric renders (the defocus stage's images, before any later stage) of one process,
    kept for renders of the same shots with other later stages: a benchmark draws one scene
    with several effects sets (``lensfit.bench``), whose images differ only after the geometric
    render. An entry's key is a digest of everything that render reads (method, shot, camera,
    the tracer's aperture, front stop and warp, samples per pixel, seed, background,
    supersampling); a hit hands out a copy, bit for bit the image a new render would give.

    ``entries``: key -> {"image", "fine" (its cells, k x k a pixel, or None), "factor" (that k, 1
    without), "window": (start, end) in ``time.time()`` of its render};
    ``hits``: the keys handed out, in order (the caller accounts for their seconds)."""

    def __init__(self) -> None:
        self.entries: dict[str, dict[str, Any]] = {}
        self.hits: list[str] = []


def _canonical(obj, depth: int = 0):
    """A value's content, exactly, as nested tuples (dataclass fields, array bytes, floats in
    hex): equal for equal content however the objects were built (a pickle is not: it carries
    cached attributes and shared references)."""
    import dataclasses

    if depth > 12:
        raise ValueError("too deep")
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return (type(obj).__qualname__,) + tuple((f.name, _canonical(getattr(obj, f.name), depth + 1))
                                                 for f in dataclasses.fields(obj))
    if isinstance(obj, np.ndarray):
        return ("array", obj.dtype.str, obj.shape, obj.tobytes())
    if isinstance(obj, float):
        return ("float", obj.hex())
    if isinstance(obj, (bool, int, str, bytes, type(None))):
        return obj
    if isinstance(obj, (np.generic,)):
        return ("np", obj.dtype.str, obj.tobytes())
    if isinstance(obj, (tuple, list)):
        return (type(obj).__name__,) + tuple(_canonical(v, depth + 1) for v in obj)
    if isinstance(obj, dict):
        return ("dict",) + tuple(sorted((repr(k), _canonical(v, depth + 1)) for k, v in obj.items()))
    raise ValueError(f"no canonical form for {type(obj).__name__}")


def _geometric_key(*parts) -> str | None:
    import hashlib

    try:
        return hashlib.sha256(repr(_canonical(parts)).encode()).hexdigest()
    except (ValueError, TypeError):  # something without a canonical form: no sharing, never a wrong image
        return None


#: The most cells a side the bench's shared renders keep (at 256 spp 8 would hold 64 floats a
#: pixel); a later render with diffraction that wants more renders again.
FINE_SHARED = 4


def render_shot(scene: Scene, sp: ShotPlan, k: int, tick: Callable[[int], None],
                cache: GeometricCache | None = None):
    """One shot through its stages: (linear radiance float32 (H, W) or (H, W, 3), raw DN uint16
    or None, per-image truth entries, seconds per stage). The geometric render (defocus: the
    aperture, optical vignetting, exact distortion and per-channel focus act inside it) here,
    then the stages the scene calls for (``synth.effects.stages``)."""
    r, fx, shot = scene.render, scene.effects, sp.shot
    seconds: dict[str, float] = {}
    last = [time.perf_counter()]

    def lap(stage: str) -> None:
        now = time.perf_counter()
        seconds[stage] = seconds.get(stage, 0.0) + now - last[0]
        last[0] = now

    cam = shot.camera
    ca = fx.chromatic_aberration
    waves = cam.wavelengths_nm
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
    fines: list[np.ndarray | None] = []  # the planes at `factor` times the resolution, for diffraction
    factor = fine_choice(scene, cam, sp.method) if fx.diffraction is not None else 1
    fine = factor > 1
    # The ray tracer's cell means (k x k a pixel) cost no rays: a shared render keeps them, at the
    # factor its samples allow, for a later render of the shot with diffraction (the bench's
    # effects sets), whose image they are.
    if sp.method != "raytrace":
        cells = 1
    elif fine:
        cells = factor
    else:
        cells = _shared_cells(r.samples_per_pixel) if cache is not None else 1
    distinct = len({id(c) for c in cameras})
    for c, ccam in enumerate(cameras):
        same = next((j for j in range(c) if cameras[j] is ccam), None)
        if same is not None:  # a channel the lens treats like an earlier one: no second render
            planes.append(planes[same])
            fines.append(fines[same])
            continue
        rows = (lambda n, _d=distinct: tick(n / _d)) if distinct > 1 else tick
        cam_kw = {} if ccam is cam else {"camera": ccam}
        key = None if cache is None else _geometric_key(
            sp.method, shot, ccam, kwargs_rt, r.samples_per_pixel, raytrace_seed(r.seed, k), scene.background_value,
            r.supersampling, fx.aperture, r.mitsuba_variant, factor if sp.method == "convolve" and fine else False)
        entry = None if key is None else cache.entries.get(key)
        if entry is not None and (not fine or entry["factor"] % factor == 0):
            if sp.method == "mitsuba":  # what Mitsuba refuses depends on the effects, which the key leaves out
                from synth.mitsuba import check

                check(shot, fx)
            planes.append(entry["image"].copy())
            fines.append(_cells(entry["fine"], entry["factor"] // factor) if fine else None)
            cache.hits.append(key)
            rows(ccam.height_px)
            continue
        started = time.time()
        img, img_fine = REGISTRY[sp.method].render(RenderJob(
            shot, scene.background_value, r.samples_per_pixel, raytrace_seed(r.seed, k), r.supersampling, rows,
            camera=cam_kw.get("camera"), raytrace_options=kwargs_rt, effects=fx, mitsuba_variant=r.mitsuba_variant,
            cells=cells, factor=factor))
        if key is not None:
            cache.entries[key] = {"image": img.copy(), "fine": None if img_fine is None else img_fine.copy(),
                                  "factor": 1 if img_fine is None else img_fine.shape[0] // img.shape[0],
                                  "window": (started, time.time())}
        planes.append(img)
        fines.append(img_fine if fine else None)
    if waves:
        from synth.spectral import combine

        image = combine(planes, waves, fx.channels)
        image_fine = combine(fines, waves, fx.channels) if fine else None
    else:
        image = planes[0] if len(planes) == 1 else np.stack(planes, axis=-1)
        image_fine = (fines[0] if len(fines) == 1 else np.stack(fines, axis=-1)) if fine else None
    lap("defocus")
    state = run_stages(ShotState(image, scene, shot, sp.method, k, fine=image_fine, fine_factor=factor), lap)
    return state.image, state.raw, state.extra, seconds


def _shared_cells(spp: int) -> int:
    """The cells a side a shared ray-traced render keeps for a later render with diffraction."""
    return next(k for k in (FINE_SHARED, 2, 1) if cell_factor(spp) % k == 0)


def _cells(fine: np.ndarray, n: int) -> np.ndarray:
    """A copy of ``fine`` with each n x n block of its cells merged into their mean (n = 1: the
    cells as they are)."""
    return fine.copy() if n == 1 else block_mean(fine, n)


def _mitsuba_version(variant: str) -> str:
    from synth.mitsuba import version

    return version(variant)


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
           mitsuba_variant: str | None = None,
           progress: Callable[[str, int, int], None] | None = None,
           geometric_cache: GeometricCache | None = None) -> RenderResult:
    """Render every shot of a scene; deterministic for a seed.

    Parameters
    ----------
    scene : Scene or str or Path
        A loaded scene, or the path of a scene TOML file.
    method : str, optional
        Overrides ``render.method``: "auto", "raytrace", "convolve" or "mitsuba".
    samples_per_pixel : int, optional
        Overrides ``render.samples_per_pixel`` (ray tracing; a square number stratifies best).
    seed : int, optional
        Overrides ``render.seed``.
    supersampling : int, optional
        Overrides ``render.supersampling`` (the convolution renderer's sub-pixels a side).
    image_format : str, optional
        Overrides ``render.format``: one of ``IMAGE_FORMATS``.
    mitsuba_variant : str, optional
        One of ``synth.mitsuba.VARIANTS``.
    progress : callable, optional
        Called as ``progress(shot_name, done_rows, total_rows)`` as rows finish.
    geometric_cache : GeometricCache, optional
        Shared by renders of one scene with different later stages (effects after the geometric
        render): each shot's geometric image is rendered once and handed out again, bit for bit.

    Returns
    -------
    RenderResult

    Examples
    --------
    >>> import synth
    >>> result = synth.render("data_specs/scenes/demo.toml", samples_per_pixel=16, seed=1)  # doctest: +SKIP
    >>> sorted(result.images)[:2], result.truth["focal_length_mm"]                         # doctest: +SKIP
    (['shot_000.png', 'shot_001.png'], 25.0)
    >>> synth.write_stack(result, "out/my_stack")                                            # doctest: +SKIP
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    check_overrides(samples_per_pixel=samples_per_pixel, supersampling=supersampling, seed=seed)
    if image_format is not None and image_format not in IMAGE_FORMATS:
        raise InputError("image_format", image_format, "one of " + ", ".join(IMAGE_FORMATS))
    problem = scene.effects.format_problem(image_format) if image_format is not None else None
    if problem is not None:
        raise InputError("image_format", image_format, *problem)
    if mitsuba_variant is not None and mitsuba_variant not in MITSUBA_VARIANTS:
        raise InputError("mitsuba_variant", mitsuba_variant, "one of " + ", ".join(MITSUBA_VARIANTS))
    scene = scene.with_render(method=method, samples_per_pixel=samples_per_pixel, seed=seed,
                              supersampling=supersampling, format=image_format, mitsuba_variant=mitsuba_variant)
    r = scene.render
    result = RenderResult(image_format=r.format, jpeg_quality=r.jpeg_quality)
    images_truth, settings = [], {}
    methods_used = set()
    plans = plan(scene)
    widest = widest_f_number(scene)
    for k, sp in enumerate(plans):
        shot, cam = sp.shot, sp.shot.camera
        name = shot.name + image_extension(r.format)
        done = [0]

        def tick(n, _name=shot.name, _h=cam.height_px):
            done[0] += n
            if progress is not None:
                progress(_name, done[0], _h)

        img, raw, extra, seconds = render_shot(scene, sp, k, tick, geometric_cache)
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
                                if "exposure" in extra else {}),
                             **({"widest_f_number": widest} if widest is not None else {})}
        depth = chief_ray_depth(shot, scene.effects.distortion)
        coc = np.asarray(cam.coc_diameter_px(depth))
        map_file = f"truth/{shot.name}_maps.npz"
        result.maps[map_file] = {"depth_mm": depth.astype(np.float32), "coc_diameter_px": coc.astype(np.float32)}
        settings.setdefault(shot.setting, {
            "focal_length_mm": cam.focal_length_mm,
            "f_number": cam.f_number,
            "focus_distance_mm": finite_or_none(cam.focus_distance_mm),
            "inverse_focus_distance_per_mm": cam.inverse_focus_distance_per_mm,
            "sensor_distance_mm": cam.sensor_distance_mm,
            "focus_distance_from_sensor_mm": finite_or_none(cam.focus_distance_mm + cam.sensor_distance_mm),
            "aperture_diameter_mm": cam.aperture_diameter_mm,
            "focal_length_px": cam.focal_length_px,
            **(cam.truth() if cam.prescription is not None else {}),
        })
        images_truth.append({
            "file": name, "shot": shot.name, "setting": shot.setting,
            "method": sp.method, "method_exact": sp.exact, "method_reason": sp.reason,
            "samples_per_pixel": r.samples_per_pixel if sp.method in ("raytrace", "mitsuba") else None,
            "supersampling": r.supersampling if sp.method == "convolve" else None,
            "seed": raytrace_seed(r.seed, k) if sp.method in ("raytrace", "mitsuba") else None,
            "stages": list(sp.stages),
            **extra,
            "maps": map_file,
            "targets": [target_truth(o, shot, scene.effects.distortion) for o in shot.objects],
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
        "method": next(iter(methods_used)) if len(methods_used) == 1 else "mixed",
        **({"renderer": _mitsuba_version(r.mitsuba_variant)} if "mitsuba" in methods_used else {}),
        "method_requested": r.method,
        "samples_per_pixel": r.samples_per_pixel,
        "supersampling": r.supersampling,
        "seed": r.seed,
        "intensity": "linear radiance; 16-bit files hold round(65535 * clip(value, 0, 1))",
        "conventions": "data_specs/CONVENTIONS.md",
        "version": __version__,
        "provenance": provenance("synth", dated=False),  # the same record as lensfit's files
    }
    result.manifest = stack_manifest(scene, [i["file"] for i in images_truth], [i["setting"] for i in images_truth],
                                     [[o.target.id for o in sp.shot.objects] for sp in plans])
    if r.format not in ("dng", "jpeg"):  # JPEGs hold the levels applied
        for entry in result.manifest["image"]:
            entry.update(result.levels.get(entry["file"], {}))
    return result

