"""The image stages after the geometric (defocus) render, registered in one place.

Each stage belongs to one effect and owns, in one class, what the pipeline needs of it: whether
the scene calls for it (``wanted``), how ``synth plan`` names it and what it costs (``describe``,
seconds estimated per shot), and what it does to the image and records in the truth
(``apply``). ``STAGES`` lists them in the order light meets them; ``synth.rendering`` runs the ones
a scene wants, ``synth.planning`` lists them. A stage the scene does not call for is not
constructed into the shot's list: it costs nothing and changes nothing.

The effects' models and parameters stay in their modules (``synth/effects/<name>.py``); their
scene tables are parsed in ``synth.effects`` (``Effects``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np


@dataclass
class ShotState:
    """What flows through the stages of one shot: the linear image, the sensor signal in
    electrons (exposure), the read noise drawn, the raw DN (readout or mosaic), the per-image
    truth entries, and the context (scene, shot, method, shot index)."""

    image: np.ndarray
    scene: Any
    shot: Any
    method: str
    index: int
    signal: np.ndarray | None = None
    read: np.ndarray | None = None
    raw: np.ndarray | None = None
    exposure: Any = None  # the shot's exposure settings (ExposureStage), read out by ReadoutStage
    extra: dict[str, Any] = field(default_factory=dict)
    #: the geometric render at ``fine_factor`` times the resolution, where the renderer gave one
    #: for diffraction (:func:`fine_choice`); its k x k means are ``image``
    fine: np.ndarray | None = None
    fine_factor: int = 1

    @property
    def effects(self):
        return self.scene.effects

    @property
    def camera(self):
        return self.shot.camera


def working_f_number(camera) -> float:
    """Image-side f-number s/A (N at infinity focus; 2N at 1:1)."""
    return camera.sensor_distance_mm / camera.aperture_diameter_mm


def fine_factor(method: str, samples_per_pixel: int, supersampling: int) -> int:
    """The most times the resolution (per axis) a render method gives the geometric render at, at
    no extra cost, for diffraction to act on (``synth.effects.diffraction``; 1: none): the
    convolution renderer its sub-pixels (8, 4 or 2 x as many to a pixel's side as divide its
    supersampling), the ray tracer its strata (``synth.raytrace.cell_factor``: 4 at 16 spp, 8 at
    64 or 256). :func:`fine_choice` chooses within it."""
    from synth.raytrace import cell_factor

    if method == "convolve":
        return next((k for k in (8, 4, 2) if supersampling % k == 0), 1)
    return cell_factor(samples_per_pixel) if method == "raytrace" else 1


#: The factor a diffraction render asks for (:func:`fine_choice`): 4, and 8 where the Airy scale
#: ``a = lambda N_w / p`` is under FINE_8_BELOW_AIRY_PX (synth.effects.diffraction: at a = 0.22 px
#: a 0.29 px blur read 0.0-0.36 px by its phase at 4, 0.28-0.32 at 8).
FINE_8_BELOW_AIRY_PX = 0.5


def fine_choice(scene, camera, method: str) -> int:
    """How many times the resolution (per axis) a shot's geometric render comes at as well, for
    diffraction to act on the irradiance before the pixels integrate it
    (``synth.effects.diffraction``): 4, or 8 under a small Airy pattern (FINE_8_BELOW_AIRY_PX),
    as far as the method's samples allow (:func:`fine_factor`) and within the memory budget
    (else the next smaller); 1 where none: diffraction then filters the image as sampled (an
    approximation; the truth says which)."""
    from lensfit.io.limits import RENDER_MEMORY_BYTES
    from synth.effects import diffraction

    r, params, n_w = scene.render, scene.effects.diffraction, working_f_number(camera)
    most = fine_factor(method, r.samples_per_pixel, r.supersampling)
    airy_px = min(params.wavelength_nm) * 1e-6 * n_w / camera.pixel_pitch_mm
    wanted = 8 if airy_px < FINE_8_BELOW_AIRY_PX else 4
    for k in (8, 4, 2):
        if k > wanted or most % k:
            continue
        if diffraction.bytes_needed(params, n_w, camera.pixel_pitch_mm / k, k * camera.width_px,
                                    k * camera.height_px) <= RENDER_MEMORY_BYTES:
            return k
    return 1


def quantise_16bit(image: np.ndarray) -> np.ndarray:
    """Linear radiance -> uint16: round(65535 * clip(v, 0, 1))."""
    return np.round(np.clip(image, 0.0, 1.0) * 65535.0).astype(np.uint16)


class Stage:
    """One stage: ``name`` (its key in the per-stage seconds), ``wanted``, ``describe``, ``apply``."""

    name = ""

    def wanted(self, fx, method: str) -> bool:
        raise NotImplementedError

    def describe(self, scene, shot, method: str) -> list[tuple[str, float]]:
        """Rows (label for ``synth plan``, estimated seconds)."""
        raise NotImplementedError

    def apply(self, state: ShotState) -> bool | None:
        """Transform ``state``; False where nothing took time (the work happened elsewhere)."""
        raise NotImplementedError


class DiffractionStage(Stage):
    name = "diffraction"

    def wanted(self, fx, method):
        return fx.diffraction is not None

    def describe(self, scene, shot, method):
        from synth.effects import diffraction

        cam, fx = shot.camera, scene.effects
        waves = "/".join(f"{w:g}" for w in fx.diffraction.wavelength_nm)
        k = fine_choice(scene, cam, method)
        return [(f"diffraction (Airy, {waves} nm{f', on the {k}x render' if k > 1 else ''})",
                 diffraction.seconds(k * cam.width_px, k * cam.height_px, fx.channels))]

    def apply(self, state):
        from synth.effects import diffraction

        fx, cam = state.effects, state.camera
        Nw = working_f_number(cam)
        if state.fine is not None:  # on the irradiance, then integrated over each pixel
            state.image = diffraction.apply_fine(state.fine, fx.diffraction, Nw, cam.pixel_pitch_mm, state.fine_factor)
            applied = diffraction.applied_fine(state.fine_factor)
            state.fine = None
        else:
            state.image = diffraction.apply(state.image, fx.diffraction, Nw, cam.pixel_pitch_mm).astype(np.float32)
            applied = diffraction.APPLIED_SAMPLED
        state.extra["diffraction"] = {**fx.diffraction.truth(Nw, cam.pixel_pitch_mm), "applied": applied}


class VignettingStage(Stage):
    name = "vignetting"

    def wanted(self, fx, method):
        return fx.vignetting is not None

    def describe(self, scene, shot, method):
        v, cam = scene.effects.vignetting, shot.camera
        parts = (["cos^4"] if v.natural else []) + (["front stop in the ray tracer"] if v.optical else [])
        pixels = cam.width_px * cam.height_px
        return [(f"vignetting ({', '.join(parts) or 'none'})",
                 5e-9 * pixels * scene.effects.channels if v.natural else 0.0)]

    def apply(self, state):
        if state.effects.vignetting.natural:  # optical vignetting happened in the ray tracer
            from synth.effects import vignetting

            state.image = vignetting.apply_natural(state.image, state.camera)
            return True
        return False


class DistortionStage(Stage):
    """Distortion (exact in the ray tracer, else one cubic resampling) and lateral chromatic
    aberration (the same resampling); the longitudinal part acts in the defocus stage."""

    name = "distortion"

    def wanted(self, fx, method):
        return fx.distortion is not None or fx.chromatic_aberration is not None

    def describe(self, scene, shot, method):
        fx, cam = scene.effects, shot.camera
        pixels = cam.width_px * cam.height_px
        lateral = fx.chromatic_aberration is not None and fx.chromatic_aberration.lateral
        rows = []
        if fx.distortion is not None and method == "raytrace":
            rows.append(("distortion (exact, in the ray tracer)", 4e-7 * pixels))
        if lateral or (fx.distortion is not None and method != "raytrace"):
            name = "lateral CA" if method == "raytrace" or fx.distortion is None else (
                "distortion" + (" + lateral CA" if lateral else ""))
            rows.append((f"{name} (cubic resampling)", 1.5e-7 * pixels * fx.channels
                         + (4e-7 * pixels if fx.distortion is not None and method != "raytrace" else 0.0)))
        if fx.chromatic_aberration is not None and fx.chromatic_aberration.longitudinal:
            rows.append(("chromatic_aberration (longitudinal: per-channel focus, in the defocus stage)", 0.0))
        return rows

    def apply(self, state):
        fx, cam = state.effects, state.camera
        ca = fx.chromatic_aberration
        exact = fx.distortion is not None and state.method == "raytrace"
        lateral = ca is not None and ca.lateral
        timed = False
        if (fx.distortion is not None and not exact) or lateral:
            from synth.effects import distortion

            state.image = distortion.warp(state.image, cam, None if exact else fx.distortion,
                                          ca.magnification if lateral else None)
            timed = True
        if fx.distortion is not None:
            state.extra["distortion"] = {
                **fx.distortion.truth(cam.focal_length_px, cam.principal_point_px),
                "applied": ("in the ray tracer (each sample's own undistorted ray)" if exact
                            else "cubic resampling of the rendered image")}
        if ca is not None:
            state.extra["chromatic_aberration"] = ca.truth(cam)
        return timed


class ExposureStage(Stage):
    """Scene radiance -> mean electrons (exposure); the readout to DN is ``ReadoutStage``."""

    name = "exposure"

    def wanted(self, fx, method):
        return fx.exposure is not None

    def describe(self, scene, shot, method):
        from synth.effects import exposure

        fx, cam = scene.effects, shot.camera
        e = fx.exposure.for_shot(shot.shutter_s, shot.iso)
        iso = e.iso if e.iso is not None else fx.sensor.base_iso
        return [(f"exposure ({e.shutter_s:g} s, ISO {iso:g}, {fx.sensor.name})",
                 exposure.seconds(cam.width_px, cam.height_px))]

    def apply(self, state):
        from synth.effects import exposure

        fx = state.effects
        state.exposure = fx.exposure.for_shot(state.shot.shutter_s, state.shot.iso)
        state.signal = exposure.mean_electrons(state.image, state.exposure, fx.sensor, working_f_number(state.camera),
                                               fx.aperture.area_fraction)


class MosaicStage(Stage):
    name = "mosaic"

    def wanted(self, fx, method):
        return fx.mosaic is not None

    def describe(self, scene, shot, method):
        cam = shot.camera
        return [(f"mosaic ({scene.effects.mosaic.pattern})", 1e-8 * cam.width_px * cam.height_px)]

    def apply(self, state):
        from synth.effects import mosaic

        fx = state.effects
        if state.signal is not None:  # electrons: the readout quantises
            state.signal = mosaic.apply(state.signal, fx.mosaic)
        else:  # no sensor model: the mosaic of the linear image, quantised to 16 bits
            state.raw = quantise_16bit(mosaic.apply(state.image, fx.mosaic))


class NoiseStage(Stage):
    name = "noise"

    def wanted(self, fx, method):
        return fx.noise is not None

    def describe(self, scene, shot, method):
        from synth.effects import noise

        return [("noise (shot + read)", noise.seconds(shot.camera.width_px, shot.camera.height_px))]

    def apply(self, state):
        from synth.effects import noise

        fx = state.effects
        state.signal, state.read = noise.draw(state.signal, fx.noise, fx.sensor.read_noise_e,
                                              noise.generator(state.scene.render.seed, state.index))


class ReadoutStage(Stage):
    """Electrons -> DN (the exposure effect's sensor); its truth entry is the exposure's."""

    name = "readout"

    def wanted(self, fx, method):
        return fx.exposure is not None

    def describe(self, scene, shot, method):
        cam = shot.camera
        return [(f"readout ({scene.effects.sensor.bit_depth}-bit DN)", 5e-9 * cam.width_px * cam.height_px)]

    def apply(self, state):
        from synth.effects import exposure

        fx, e = state.effects, state.exposure
        iso = e.iso if e.iso is not None else fx.sensor.base_iso
        state.raw = exposure.readout(state.signal, fx.sensor, iso, state.read)
        state.extra["exposure"] = exposure.truth(e, fx.sensor, working_f_number(state.camera),
                                                 fx.aperture.area_fraction)


#: Every stage after the geometric render, in the order light meets them.
STAGES: tuple[Stage, ...] = (DiffractionStage(), VignettingStage(), DistortionStage(), ExposureStage(),
                             MosaicStage(), NoiseStage(), ReadoutStage())


def wanted_stages(fx, method: str) -> list[Stage]:
    """The stages a scene's effects call for, in pipeline order."""
    return [s for s in STAGES if s.wanted(fx, method)]


def run_stages(state: ShotState, lap: Callable[[str], None]) -> ShotState:
    """Apply every wanted stage to ``state``; ``lap(name)`` closes each timed stage."""
    for stage in wanted_stages(state.effects, state.method):
        if stage.apply(state) is not False:
            lap(stage.name)
    return state
