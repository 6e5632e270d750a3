"""``method = "mitsuba"``: the geometric render done by another renderer, Mitsuba 3.

A stack rendered this way shares nothing with synth's own ray tracer or convolution but the
scene (the targets' reflectance and their poses): the camera, the thin lens's defocus, the
sampling of the aperture and the pixel, and the texture lookup are Mitsuba's. It is the
independent check the fit's accuracy and intervals are judged by (``lensfit bench --suite
independent``) and a cross-check of synth's ray tracer (``tests/test_mitsuba.py``).

How the scene maps onto Mitsuba 3 (``scalar_rgb`` variant: CPU only, no LLVM needed):

- the ``thinlens`` sensor at the lens centre looking along +z, image x right and y down (the
  camera frame of ``data_specs/CONVENTIONS.md``), its pinhole field of view from the sensor
  distance ``s`` (``tan(fov_x / 2) = W p / (2 s)``: a thin lens images a point where the
  chief ray through its centre meets the sensor), ``aperture_radius = A / 2`` and
  ``focus_distance`` = the focus distance from the lens plane; the principal point is the
  image centre, as in synth;
- the box pixel filter (``rfilter = box``: the pixel's area, 100 % fill factor) and
  ``independent`` sampling with ``samples_per_pixel`` paths and the shot's seed;
- each target a ``rectangle`` whose front emits its reflectance (an ``area`` emitter with a
  ``bitmap`` radiance looked up nearest-neighbour: a ChArUco board is OpenCV's raster with
  whole texels per square and marker cell, a checkerboard one texel per square, so both are
  exact; an ``image`` target bilinear, as in synth); the background a ``constant`` emitter of
  the scene's background value; the ``direct`` integrator, which returns what a camera ray
  sees first (a black BSDF: the targets reflect nothing).

Refused (with the reason): compound lenses, wavelengths and longitudinal chromatic aberration,
non-circular apertures, optical vignetting, and the analytic targets (``slanted-edge``,
``siemens-star``), which a texel raster would only approximate. Effects after the geometric
render (distortion as a resampling stage, diffraction, exposure, noise, mosaic) run as they do
after ``convolve``.

Mitsuba is a test dependency (``pip install mitsuba``), not a core one; it renders about
4.6 M samples per second on 2 cores here, a tenth of what synth's own tracer does (README).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from lensfit.errors import InputError
from synth import textures

#: Image rows rendered per call (a crop of the film): progress is reported per band.
BAND_ROWS = 64
SUPPORTED_TEXTURES = ("raster-nearest", "raster-bilinear", "checkerboard", "uniform")


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - the test extra installs it
        raise InputError("method", "mitsuba", "raytrace, convolve or auto, or install Mitsuba 3",
                         f"Mitsuba 3 is not installed ({e}); pip install mitsuba") from None
    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


def version() -> str:
    """The Mitsuba version and variant a render used (for truth.json)."""
    mi = _mitsuba()
    return f"Mitsuba {mi.__version__} {mi.variant()}"


def unsupported(shot, effects) -> str | None:
    """Why Mitsuba cannot render this shot as the scene asks, or None."""
    cam = shot.camera
    if getattr(cam, "prescription", None) is not None:
        return f"the compound lens {cam.prescription.name} (Mitsuba's thinlens camera is a thin lens)"
    if getattr(cam, "wavelengths_nm", ()):
        return "lens.wavelengths_nm (spectral rendering through a compound lens)"
    if effects is not None:
        ca = effects.chromatic_aberration
        if ca is not None and ca.longitudinal:
            return "longitudinal chromatic aberration (one focus per channel)"
        if effects.aperture.shape != "circle":
            return f"a {effects.aperture.shape} aperture (Mitsuba's thinlens aperture is a disk)"
        if effects.needs_raytrace:
            return effects.needs_raytrace
    for o in shot.objects:
        kind = textures.texture(o.target).static[0]
        if kind not in SUPPORTED_TEXTURES:
            return (f"target {o.target.id!r} of kind {o.target.target!r} (analytic edges a texel raster would "
                    "only approximate)")
    return None


def check(shot, effects) -> None:
    """Refuse (InputError naming the method and the reason) a shot Mitsuba cannot render."""
    why = unsupported(shot, effects)
    if why is not None:
        raise InputError("method", "mitsuba", "raytrace or auto for this scene", f"Mitsuba cannot render {why}")


def _bitmap_radiance(mi, target) -> dict:
    """The target's reflectance as a Mitsuba bitmap texture over the rectangle's (u, v)."""
    tex = textures.texture(target)
    kind = tex.static[0]
    w, h = target.size_mm
    if kind == "uniform":
        return {"type": "rgb", "value": float(tex.static[3])}
    if kind == "checkerboard":
        _, _, _, (nx, ny), sq, dark, light = tex.static
        j, i = np.mgrid[0:ny, 0:nx]
        raster, margin, pw, ph = np.where((i + j) % 2 == 0, dark, light), light, nx * sq, ny * sq
    elif kind == "raster-nearest":
        _, _, _, pw, ph, margin = tex.static
        raster = np.asarray(tex.raster)
    else:  # raster-bilinear: the image spans the whole target
        raster, margin, pw, ph = np.asarray(tex.raster), None, w, h
    rows, cols = raster.shape
    if margin is not None:  # one texel of margin on each side; beyond it the lookup clamps to it
        raster = np.pad(raster, 1, constant_values=margin)
        pw, ph = pw * (cols + 2) / cols, ph * (rows + 2) / rows
    # rectangle (u, v) in [0, 1]^2 spans the target's w x h mm (u along x, v along y, down);
    # the raster spans pw x ph mm about the same centre
    to_uv = (mi.ScalarTransform4f().translate([0.5, 0.5, 0.0]) @ mi.ScalarTransform4f().scale([w / pw, h / ph, 1.0])
             @ mi.ScalarTransform4f().translate([-0.5, -0.5, 0.0]))
    rgb = np.repeat(np.asarray(raster, np.float32)[..., None], 3, axis=2)
    return {"type": "bitmap", "bitmap": mi.Bitmap(rgb), "raw": True, "wrap_mode": "clamp", "to_uv": to_uv,
            "filter_type": "bilinear" if kind == "raster-bilinear" else "nearest"}


def _targets(mi, shot) -> dict:
    """The shot's targets as loaded Mitsuba shapes (built once; every band of rows shares them)."""
    out = {}
    for k, o in enumerate(shot.objects):
        w, h = o.target.size_mm
        R, t = o.pose.R_cam_target, o.pose.t_cam_target
        M = np.eye(4)
        # Mitsuba's rectangle is [-1, 1]^2 in its x-y plane, emitting towards +z: scaled to the
        # target and turned so that its front faces the camera (target -z)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = R[:, 0] * (0.5 * w), R[:, 1] * (0.5 * h), -R[:, 2], t
        out[f"target_{k}"] = mi.load_dict({
            "type": "rectangle", "to_world": mi.ScalarTransform4f(M),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
            "emitter": {"type": "area", "radiance": _bitmap_radiance(mi, o.target)}})
    return out


def scene_dict(shot, background: float, spp: int, seed: int, rows: tuple[int, int] | None = None,
               targets: dict | None = None) -> dict:
    """The Mitsuba scene of one shot (optionally only image rows ``rows = (first, count)``;
    ``targets``: the shapes of :func:`_targets`, when already built)."""
    mi = _mitsuba()
    cam = shot.camera
    W, H = cam.width_px, cam.height_px
    fov_x = 2.0 * math.degrees(math.atan(W * cam.pixel_pitch_mm / (2.0 * cam.sensor_distance_mm)))
    film = {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}, "pixel_format": "rgb"}
    if rows is not None:
        film.update(crop_offset_x=0, crop_offset_y=rows[0], crop_width=W, crop_height=rows[1])
    focus = cam.focus_distance_mm if math.isfinite(cam.focus_distance_mm) else 1e12
    out = {"type": "scene", "integrator": {"type": "direct"},
           "background": {"type": "constant", "radiance": {"type": "rgb", "value": float(background)}},
           "sensor": {"type": "thinlens", "fov": fov_x, "fov_axis": "x",
                      "aperture_radius": 0.5 * cam.aperture_diameter_mm, "focus_distance": focus,
                      "near_clip": 1e-3, "far_clip": 1e12,
                      "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
                      "film": film,
                      "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)}}}
    out.update(targets if targets is not None else _targets(mi, shot))
    return out


def render_mitsuba(shot, background: float, spp: int, seed: int, progress: Callable[[int], None] | None = None,
                   effects=None) -> np.ndarray:
    """Render one shot with Mitsuba 3; linear radiance, float32 (height, width).

    Rendered in bands of ``BAND_ROWS`` rows (``progress(n)`` after each), each band with its own
    sampler seed derived from ``seed``: deterministic for a seed.
    """
    check(shot, effects)
    mi = _mitsuba()
    H = shot.camera.height_px
    out = np.empty((H, shot.camera.width_px), np.float32)
    targets = _targets(mi, shot)
    for band, r0 in enumerate(range(0, H, BAND_ROWS)):
        n = min(BAND_ROWS, H - r0)
        scene = mi.load_dict(scene_dict(shot, background, spp, (seed * 7919 + band) % 2**31, rows=(r0, n),
                                        targets=targets))
        out[r0:r0 + n] = np.asarray(mi.render(scene), np.float32)[..., 0]
        if progress is not None:
            progress(n)
    return out
