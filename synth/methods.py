"""The geometric render methods, registered in one place as the image stages are
(``synth.effects.stages``). Each owns, in one class, what the pipeline needs of it: what
``synth plan`` estimates it costs (``estimate``), the memory it needs beyond the images, refused
before anything is allocated (``check_memory``), and the render itself (``render``). Which one a
shot takes is ``synth.planning.choose_method``'s decision; ``synth.rendering`` calls it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from lensfit.errors import InputError
from lensfit.io.limits import RENDER_MEMORY_BYTES, format_bytes
from synth.convolve import blurred_footprint_px, convolve_bytes

#: Rough throughputs on a 2-core machine, used only for the cost estimates of ``synth plan``.
# synth bench: ~320 M/s on a flat board, ~260 on a tilted one, compiled, every pixel traced; an upper
# bound on a render's time, which samples only the pixels outside constant regions (synth.flat: 5-35 % on the demo)
RAYTRACE_SAMPLES_PER_S = 250e6
# synth bench --plan-costs: 32-38 M lens samples x surfaces per second through the four shipped designs
# (6-13 surfaces, 16 and 64 spp); every pixel is traced through a compound lens
COMPOUND_SURFACE_SAMPLES_PER_S = 34e6
CONVOLVE_SUBPIXELS_PER_S = 25e6
MITSUBA_SAMPLES_PER_S = 4.5e6  # Mitsuba 3 scalar_rgb, thinlens, direct (synth.mitsuba; synth bench --against-mitsuba)


@dataclass(frozen=True)
class RenderJob:
    """One geometric render of one shot: its background radiance, samples per pixel and seed
    (the ray tracers'), sub-pixels a side (the convolution's), ``rows`` (progress, rows done),
    ``camera`` (a colour channel's or a wavelength's in place of the shot's; None: the shot's),
    the ray tracer's extras (aperture shape, front stop, distortion warp), the effects, the
    Mitsuba variant, and the finer render diffraction asks for: ``cells`` (the ray tracer's k x k
    cell means a pixel) or ``factor`` (the convolution's)."""

    shot: Any
    background: float
    samples_per_pixel: int
    seed: int
    supersampling: int
    rows: Callable[[int], None]
    camera: Any = None
    raytrace_options: dict[str, Any] = field(default_factory=dict)
    effects: Any = None
    mitsuba_variant: str = "scalar_rgb"
    cells: int = 1
    factor: int = 1

    @property
    def camera_options(self) -> dict[str, Any]:
        return {} if self.camera is None else {"camera": self.camera}


class RenderMethod:
    """A geometric render method (see the module notes)."""

    name = ""

    def estimate(self, shot: Any, samples_per_pixel: int, supersampling: int) -> tuple[float, str]:
        """(seconds on 2 cores after compilation, the work in words)."""
        raise NotImplementedError

    def check_memory(self, shot: Any, supersampling: int) -> None:
        """Refuse, naming the option, a shot whose render would take more than the memory budget."""

    def render(self, job: RenderJob) -> tuple[np.ndarray, np.ndarray | None]:
        """(linear radiance float32 (H, W), the finer render diffraction asked for, or None)."""
        raise NotImplementedError


#: name -> method, in the order ``synth plan`` and ``--method`` list them.
REGISTRY: dict[str, RenderMethod] = {}


def register(cls: type[RenderMethod]) -> type[RenderMethod]:
    REGISTRY[cls.name] = cls()
    return cls


@register
class RayTrace(RenderMethod):
    """Every pixel's lens samples traced to the scene (thin lens or a compound prescription)."""

    name = "raytrace"

    def estimate(self, shot, samples_per_pixel, supersampling):
        cam = shot.camera
        samples = cam.width_px * cam.height_px * samples_per_pixel
        rx = cam.prescription
        if rx is not None:
            n = len(rx.surfaces)
            return (samples * n / COMPOUND_SURFACE_SAMPLES_PER_S,
                    f"{samples / 1e6:.0f} M lens samples through {n} surfaces")
        return samples / RAYTRACE_SAMPLES_PER_S * max(1, len(shot.objects)) ** 0.5, f"{samples / 1e6:.0f} M lens samples"

    def check_memory(self, shot, supersampling):
        return  # two tiles of pixels in flight, 0.2 GB at most (synth.raytrace.tile_pixels)

    def render(self, job):
        from synth.raytrace import render_raytrace

        img = render_raytrace(job.shot, job.background, job.samples_per_pixel, job.seed, job.rows,
                              **job.camera_options, **job.raytrace_options, fine=job.cells)
        return img if job.cells > 1 else (img, None)


@register
class Convolve(RenderMethod):
    """Fronto-parallel targets convolved with the exact PSF on sub-pixels."""

    name = "convolve"

    def estimate(self, shot, samples_per_pixel, supersampling):
        cam = shot.camera
        sub = 0.0
        for o in shot.objects:
            u0, v0, u1, v1 = blurred_footprint_px(o, shot)
            w = max(0.0, min(u1, cam.width_px) - max(u0, 0))
            h = max(0.0, min(v1, cam.height_px) - max(v0, 0))
            sub += w * h * supersampling**2
        return sub / CONVOLVE_SUBPIXELS_PER_S + 0.05, f"{sub / 1e6:.1f} M sub-pixels convolved"

    def check_memory(self, shot, supersampling):
        need = convolve_bytes(shot, supersampling)
        if need > RENDER_MEMORY_BYTES:
            nearest = min(o.pose.t_cam_target[2] for o in shot.objects)
            raise InputError("method", "convolve", "raytrace or auto for this shot",
                             f"{shot.name}'s blur kernel and FFT grid would need {format_bytes(need)} (budget "
                             f"{format_bytes(RENDER_MEMORY_BYTES)}): its blur "
                             f"({shot.camera.coc_diameter_px(nearest):.3g} px or more) is too large to convolve; is "
                             "the focus distance meant to be so close to the focal length?")

    def render(self, job):
        from synth.convolve import render_convolve

        aperture = job.effects.aperture if job.effects is not None else None
        img = render_convolve(job.shot, job.background, job.supersampling, **job.camera_options,
                              **({"aperture": aperture} if aperture is not None and aperture.shape != "circle" else {}),
                              fine=job.factor)
        job.rows(job.shot.camera.height_px)
        return img if job.factor > 1 else (img, None)


@register
class Mitsuba(RenderMethod):
    """Mitsuba 3's thinlens camera: an independent renderer (synth.mitsuba)."""

    name = "mitsuba"

    def estimate(self, shot, samples_per_pixel, supersampling):
        cam = shot.camera
        samples = cam.width_px * cam.height_px * samples_per_pixel
        return samples / MITSUBA_SAMPLES_PER_S, f"{samples / 1e6:.0f} M lens samples (Mitsuba 3)"

    def check_memory(self, shot, supersampling):
        return  # a band of rows at a time; its film and a target's raster are small

    def render(self, job):
        from synth.mitsuba import render_mitsuba

        return render_mitsuba(job.shot, job.background, job.samples_per_pixel, job.seed, job.rows,
                              effects=job.effects, variant=job.mitsuba_variant), None
