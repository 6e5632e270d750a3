"""``method = "mitsuba"``: the geometric render done by another renderer, Mitsuba 3.

A stack rendered this way shares nothing with synth's own ray tracer or convolution but the
scene (the targets' reflectance and their poses): the camera, the thin lens's defocus, the
sampling of the aperture and the pixel, and the texture lookup are Mitsuba's. It is the
independent check the fit's accuracy and intervals are judged by (``lensfit bench --suite
independent``) and a cross-check of synth's ray tracer (``tests/synth/test_mitsuba.py``).

How the scene maps onto Mitsuba 3 (the ``scalar_rgb`` variant by default: CPU only, no LLVM
needed; ``llvm_ad_rgb``, Mitsuba's vectorised CPU variant, where libLLVM is found, see
:func:`find_libllvm`):

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

Mitsuba is a test dependency (``pip install mitsuba``; its ``llvm_ad_rgb`` variant finds the
libLLVM of ``pip install karellen-llvm-core``), not a core one. Here, on 2 cores, ``scalar_rgb``
renders about 4.6 M samples per second and ``llvm_ad_rgb`` about 25 M, against synth's own
tracer's 85 M or more (whole processes: ``synth bench --against-mitsuba``).
"""

from __future__ import annotations

import ctypes
import glob
import math
import os
import sys
from typing import Callable

import numpy as np

from lensfit.errors import InputError

#: Image rows rendered per call (a crop of the film): progress is reported per band.
BAND_ROWS = 64
SUPPORTED_TEXTURES = ("raster-nearest", "raster-bilinear", "checkerboard", "uniform")
#: Mitsuba variants a render may use: ``scalar_rgb`` (one ray at a time, no LLVM needed; the
#: default, and what the independent benchmark suite's stacks were drawn with) and ``llvm_ad_rgb``
#: (Dr.Jit's LLVM backend: vectorised and multi-threaded; needs libLLVM, :func:`find_libllvm`).
#: The two draw different samples: the same scene, not the same noise.
VARIANTS = ("scalar_rgb", "llvm_ad_rgb")


def find_libllvm() -> str | None:
    """The libLLVM shared library Dr.Jit's LLVM backend is to load: ``DRJIT_LIBLLVM_PATH`` where
    set, else the one ``pip install karellen-llvm-core`` puts under the environment's ``lib/``
    (whose C++ runtime, libc++, beside it, is loaded first: libLLVM needs it and the loader
    would not look there); None where neither is found (then Dr.Jit searches the system's)."""
    given = os.environ.get("DRJIT_LIBLLVM_PATH")
    if given:
        return given
    found = _bundled_libllvm()
    if found is None:
        return None
    runtime = os.path.join(sys.prefix, "lib", "x86_64-unknown-linux-gnu")
    for name in ("libunwind.so.1.0", "libc++abi.so.1.0", "libc++.so.1.0"):
        if os.path.exists(os.path.join(runtime, name)):
            ctypes.CDLL(os.path.join(runtime, name))  # (RTLD_LOCAL: found by its soname, shadowing nothing)
    os.environ["DRJIT_LIBLLVM_PATH"] = found
    return found


def _bundled_libllvm() -> str | None:
    """The newest libLLVM under the environment's ``lib/`` (karellen-llvm-core's), or None."""
    found = sorted(glob.glob(os.path.join(sys.prefix, "lib", "libLLVM.so.*")))
    return found[-1] if found else None


#: Oldest libLLVM whose code generator takes Dr.Jit's kernels (libLLVM 19 and older abort the
#: process on Mitsuba 3.9's: "Cannot select: fmaximum").
MIN_LLVM = (20, 0)


def load_mitsuba(variant: str = "scalar_rgb"):
    if variant not in VARIANTS:
        raise InputError("mitsuba_variant", variant, "one of " + ", ".join(VARIANTS))
    imported_before = "mitsuba" in sys.modules and "DRJIT_LIBLLVM_PATH" not in os.environ
    if "mitsuba" not in sys.modules:
        find_libllvm()  # before the import: Dr.Jit takes the library's path then
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - the test extra installs it
        raise InputError("method", "mitsuba", "raytrace, convolve or auto, or install Mitsuba 3",
                         f"Mitsuba 3 is not installed ({e}); pip install mitsuba") from None
    if mi.variant() != variant:
        fix = "scalar_rgb, or pip install karellen-llvm-core (or set DRJIT_LIBLLVM_PATH to a libLLVM 20 or later)"
        try:
            mi.set_variant(variant)
        except (ImportError, AttributeError) as e:
            raise InputError("mitsuba_variant", variant, fix,
                             f"Mitsuba's LLVM backend did not start ({str(e).splitlines()[0]})") from None
        if variant.startswith("llvm"):
            import drjit

            found = tuple(drjit.detail.llvm_version())
            if found < MIN_LLVM:
                mi.set_variant("scalar_rgb")
                late = (" (Mitsuba was imported before synth.mitsuba could point Dr.Jit at the libLLVM "
                        "of karellen-llvm-core: call synth.mitsuba.find_libllvm() first)"
                        if imported_before and _bundled_libllvm() else "")
                raise InputError("mitsuba_variant", variant, fix,
                                 f"Dr.Jit found libLLVM {'.'.join(map(str, found))}, whose code generator cannot "
                                 f"compile Mitsuba's kernels (it needs {MIN_LLVM[0]} or later){late}")
    return mi


def version(variant: str = "scalar_rgb") -> str:
    """The Mitsuba version and variant a render used (for truth.json)."""
    mi = load_mitsuba(variant)
    return f"Mitsuba {mi.__version__} {mi.variant()}"


def unsupported(shot, effects) -> str | None:
    """Why Mitsuba cannot render this shot as the scene asks, or None."""
    cam = shot.camera
    if cam.prescription is not None:
        return f"the compound lens {cam.prescription.name} (Mitsuba's thinlens camera is a thin lens)"
    if cam.wavelengths_nm:
        return "lens.wavelengths_nm (spectral rendering through a compound lens)"
    if effects is not None:
        ca = effects.chromatic_aberration
        if ca is not None and ca.longitudinal:
            return "longitudinal chromatic aberration (one focus per channel)"
        if effects.aperture.shape != "circle":
            return f"a {effects.aperture.shape} aperture (Mitsuba's thinlens aperture is a disk)"
        if effects.needs_raytrace:
            return effects.needs_raytrace
    from synth import textures

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


def _radiance(target) -> dict:
    """The target's reflectance as plain data: a uniform value, or a raster (float32, rows x
    columns) with the scale ``(sx, sy)`` from the rectangle's (u, v) to the raster's and its
    lookup (nearest or bilinear)."""
    from synth import textures

    tex = textures.texture(target)
    kind = tex.static[0]
    w, h = target.size_mm
    if kind == "uniform":
        return {"value": float(tex.static[3])}
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
    return {"raster": np.asarray(raster, np.float32), "scale": (w / pw, h / ph),
            "filter": "bilinear" if kind == "raster-bilinear" else "nearest"}


def describe(shot, background: float, spp: int, seed: int) -> dict:
    """One shot as plain data (numbers and numpy arrays, no Mitsuba objects): what
    :func:`build_scene` turns into a Mitsuba scene. ``synth bench --against-mitsuba`` hands it to
    a process that imports Mitsuba and nothing of synth's renderer."""
    cam = shot.camera
    W = cam.width_px
    targets = []
    for o in shot.objects:
        w, h = o.target.size_mm
        R, t = o.pose.R_cam_target, o.pose.t_cam_target
        M = np.eye(4)
        # Mitsuba's rectangle is [-1, 1]^2 in its x-y plane, emitting towards +z: scaled to the
        # target and turned so that its front faces the camera (target -z)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = R[:, 0] * (0.5 * w), R[:, 1] * (0.5 * h), -R[:, 2], t
        targets.append({"to_world": M, "radiance": _radiance(o.target)})
    return {"width_px": W, "height_px": cam.height_px,
            "fov_x_deg": 2.0 * math.degrees(math.atan(W * cam.pixel_pitch_mm / (2.0 * cam.sensor_distance_mm))),
            "aperture_radius_mm": 0.5 * cam.aperture_diameter_mm,
            "focus_distance_mm": cam.focus_distance_mm if math.isfinite(cam.focus_distance_mm) else 1e12,
            "background": float(background), "spp": int(spp), "seed": int(seed), "targets": targets}


def _shapes(mi, desc: dict) -> dict:
    """The described targets as loaded Mitsuba shapes (built once; every band of rows shares
    them): each a ``rectangle`` whose front emits its reflectance (a ``bitmap`` radiance over the
    rectangle's (u, v); the raster spans its own extent about the same centre)."""
    out = {}
    for k, t in enumerate(desc["targets"]):
        rad = t["radiance"]
        if "value" in rad:
            radiance = {"type": "rgb", "value": rad["value"]}
        else:
            sx, sy = rad["scale"]
            to_uv = (mi.ScalarTransform4f().translate([0.5, 0.5, 0.0]) @ mi.ScalarTransform4f().scale([sx, sy, 1.0])
                     @ mi.ScalarTransform4f().translate([-0.5, -0.5, 0.0]))
            rgb = np.repeat(rad["raster"][..., None], 3, axis=2)
            radiance = {"type": "bitmap", "bitmap": mi.Bitmap(rgb), "raw": True, "wrap_mode": "clamp",
                        "to_uv": to_uv, "filter_type": rad["filter"]}
        out[f"target_{k}"] = mi.load_dict({
            "type": "rectangle", "to_world": mi.ScalarTransform4f(t["to_world"]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
            "emitter": {"type": "area", "radiance": radiance}})
    return out


def build_scene(mi, desc: dict, rows: tuple[int, int] | None = None, seed: int | None = None,
                shapes: dict | None = None) -> dict:
    """The Mitsuba scene dict of a described shot (:func:`describe`), optionally only image rows
    ``rows = (first, count)``, with ``seed`` instead of the description's; ``shapes``: those of
    :func:`_shapes`, when already built."""
    W, H = desc["width_px"], desc["height_px"]
    film = {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}, "pixel_format": "rgb"}
    if rows is not None:
        film.update(crop_offset_x=0, crop_offset_y=rows[0], crop_width=W, crop_height=rows[1])
    out = {"type": "scene", "integrator": {"type": "direct"},
           "background": {"type": "constant", "radiance": {"type": "rgb", "value": desc["background"]}},
           "sensor": {"type": "thinlens", "fov": desc["fov_x_deg"], "fov_axis": "x",
                      "aperture_radius": desc["aperture_radius_mm"], "focus_distance": desc["focus_distance_mm"],
                      "near_clip": 1e-3, "far_clip": 1e12,
                      "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
                      "film": film,
                      "sampler": {"type": "independent", "sample_count": desc["spp"],
                                  "seed": int(desc["seed"] if seed is None else seed)}}}
    out.update(shapes if shapes is not None else _shapes(mi, desc))
    return out


def scene_dict(shot, background: float, spp: int, seed: int, rows: tuple[int, int] | None = None,
               variant: str = "scalar_rgb") -> dict:
    """The Mitsuba scene of one shot (optionally only image rows ``rows = (first, count)``;
    ``variant``: one of ``VARIANTS``)."""
    return build_scene(load_mitsuba(variant), describe(shot, background, spp, seed), rows)


def render_mitsuba(shot, background: float, spp: int, seed: int, progress: Callable[[int], None] | None = None,
                   effects=None, variant: str = "scalar_rgb") -> np.ndarray:
    """Render one shot with Mitsuba 3; linear radiance, float32 (height, width).

    ``scalar_rgb``: rendered in bands of ``BAND_ROWS`` rows (``progress(n)`` after each), each
    band with its own sampler seed derived from ``seed``; ``llvm_ad_rgb``: the whole image in one
    call with ``seed`` (one vectorised kernel over all its samples, as a Mitsuba user would call
    it; ``progress(height)`` after it). Deterministic for a seed and variant.
    """
    check(shot, effects)
    mi = load_mitsuba(variant)
    H = shot.camera.height_px
    desc = describe(shot, background, spp, seed % 2**31)
    shapes = _shapes(mi, desc)
    if variant != "scalar_rgb":
        out = np.asarray(mi.render(mi.load_dict(build_scene(mi, desc, shapes=shapes))), np.float32)[..., 0].copy()
        if progress is not None:
            progress(H)
        return out
    out = np.empty((H, shot.camera.width_px), np.float32)
    for band, r0 in enumerate(range(0, H, BAND_ROWS)):
        n = min(BAND_ROWS, H - r0)
        scene = mi.load_dict(build_scene(mi, desc, rows=(r0, n), seed=(seed * 7919 + band) % 2**31, shapes=shapes))
        out[r0:r0 + n] = np.asarray(mi.render(scene), np.float32)[..., 0]
        if progress is not None:
            progress(n)
    return out
