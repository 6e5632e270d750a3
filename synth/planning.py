"""Planning a render: the method per shot (ray tracing or exact convolution) and why, the
resources it needs (refused before any allocation beyond the budget) and the stages with their
estimated cost (``synth plan``)."""

from __future__ import annotations

from dataclasses import dataclass


from lensfit.errors import InputError
from lensfit.io.limits import RENDER_MEMORY_BYTES, format_bytes
from synth.convolve import blurred_footprint_px, convolve_bytes
from synth.methods import REGISTRY
from synth.effects import Effects
from synth.effects.stages import wanted_stages, working_f_number
from synth.scene import Scene, Shot


#: What a scene's ``render.method`` may ask for: ``auto`` (:func:`choose_method`) or a registered
#: method (``synth.methods``).
METHODS = ("auto", *REGISTRY)


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
#: about 2e-3 of the contrast (tests/synth/test_synth_render.py), so ``auto`` ray traces instead.
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


def choose_method(shot: Shot, requested: str, effects: Effects | None = None, *,
                  supersampling: int = 4) -> tuple[str, bool, str]:
    """(method, exact, reason) for one shot. ``auto`` picks the cheapest exact method that fits
    the memory budget (``lensfit.io.limits.RENDER_MEMORY_BYTES``); a method that does not fit is
    refused before anything is allocated."""
    if requested not in METHODS:
        raise InputError("method", requested, "one of " + ", ".join(METHODS))
    method, exact, why = _choose(shot, requested, effects, supersampling)
    _check_memory(shot, method, supersampling, effects)
    return method, exact, why


def _choose(shot: Shot, requested: str, effects: Effects | None, supersampling: int) -> tuple[str, bool, str]:
    if requested == "mitsuba":
        from synth.mitsuba import check

        check(shot, effects)
        return "mitsuba", True, "requested; Mitsuba 3's thinlens camera, an independent renderer (synth/mitsuba.py)"
    only_raytrace = effects.needs_raytrace if effects is not None else None
    if shot.camera.prescription is not None:
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


def _check_memory(shot: Shot, method: str, supersampling: int, effects: Effects | None) -> None:
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
    REGISTRY[method].check_memory(shot, supersampling)


def _stages(scene: Scene, shot: Shot, method: str, geometric_s: float) -> list[tuple[str, float]]:
    """(stage, estimated seconds) in pipeline order; only the effects the scene calls for (the
    stages after the geometric render describe themselves: ``synth.effects.stages``)."""
    fx, cam = scene.effects, shot.camera
    W, H, C = cam.width_px, cam.height_px, fx.channels
    pixels = W * H
    ca = fx.chromatic_aberration
    renders = 3 if ca is not None and ca.longitudinal else 1  # channels the lens treats alike share a render
    waves = cam.wavelengths_nm
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
    for stage in wanted_stages(fx, method):
        out += stage.describe(scene, shot, method)
    if fx.exposure is None:
        out.append(("quantise (16-bit)" if scene.render.format != "float-tiff" else "store (float32)", 1e-8 * pixels * C))
    return out


def plan(scene: Scene) -> list[ShotPlan]:
    """The stages each shot will run, its method and an estimated cost."""
    out = []
    r = scene.render
    for shot in scene.shots:
        method, exact, reason = choose_method(shot, r.method, scene.effects, supersampling=r.supersampling)
        seconds, work = REGISTRY[method].estimate(shot, r.samples_per_pixel, r.supersampling)
        stages = _stages(scene, shot, method, seconds)
        out.append(ShotPlan(shot, method, exact, reason, tuple(n for n, _ in stages), sum(t for _, t in stages), work,
                            tuple(t for _, t in stages)))
    return out
