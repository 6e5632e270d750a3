"""``vignetting``: light falloff towards the corners.

Model
-----
*Natural* vignetting (``natural = true``, the default): the irradiance of an image point whose
chief ray leaves the lens at angle theta to the axis falls as ``cos^4 theta`` (the cos^4 law),
with ``tan theta = r p / s`` for a point ``r`` pixels from the principal point (pitch ``p``,
sensor distance ``s``). Applied as a per-pixel factor (at the pixel centre) in both methods.

*Optical* (mechanical) vignetting, "cat's eye" bokeh: a second circular stop (the front of the
barrel) of diameter ``front_stop_diameter_mm`` at ``front_stop_distance_mm`` in front of the
aperture clips the bundle of rays to off-axis image points. A ray from lens point l towards the
in-focus point of a sensor point x_s passes the stop's plane (z = L) at
``l (1 - L/D_s) + x_s L / s``; it carries light only if that is within the stop. Simulated
exactly by ``raytrace`` (rays the stop blocks carry no light), so asking for it makes ``auto``
ray trace; the unvignetted fraction of the pupil is the overlap of two circles (a closed form,
``clear_fraction``), and blur spots become the lens-shaped overlap (cat's eye).

==============================  ======  ==============================================
parameter                       unit    meaning
==============================  ======  ==============================================
``natural``                             apply cos^4 (default true)
``front_stop_distance_mm``      mm      L > 0: distance of the clipping stop from the aperture
``front_stop_diameter_mm``      mm      B > 0: its diameter
==============================  ======  ==============================================

Reference: Ray, *Applied Photographic Optics*, 3rd ed., ch. 13 (cos^4 law, mechanical
vignetting); Kingslake, *Optical System Design* (1983), ch. 6.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NAME = "vignetting"


@dataclass(frozen=True)
class Vignetting:
    natural: bool = True
    front_stop_distance_mm: float | None = None
    front_stop_diameter_mm: float | None = None

    @property
    def optical(self) -> bool:
        return self.front_stop_distance_mm is not None

    def front_stop(self) -> tuple[float, float] | None:
        """(distance, radius) in mm for the ray tracer, or None."""
        if not self.optical:
            return None
        return (float(self.front_stop_distance_mm), 0.5 * float(self.front_stop_diameter_mm))

    def truth(self) -> dict:
        out = {"natural": "cos^4 of the chief-ray angle" if self.natural else False}
        if self.optical:
            out.update(front_stop_distance_mm=self.front_stop_distance_mm,
                       front_stop_diameter_mm=self.front_stop_diameter_mm)
        return out


def cos4_factor(width_px: int, height_px: int, principal_point_px, pixel_pitch_mm: float,
                sensor_distance_mm: float) -> np.ndarray:
    """cos^4 of the chief-ray angle at each pixel centre, float64 (H, W)."""
    cx, cy = principal_point_px
    x = (np.arange(width_px) - cx) * pixel_pitch_mm
    y = (np.arange(height_px) - cy) * pixel_pitch_mm
    tan2 = (x[None, :] ** 2 + y[:, None] ** 2) / sensor_distance_mm**2
    return 1.0 / (1.0 + tan2) ** 2


def apply_natural(image: np.ndarray, camera) -> np.ndarray:
    f = cos4_factor(camera.width_px, camera.height_px, camera.principal_point_px, camera.pixel_pitch_mm,
                    camera.sensor_distance_mm)
    return (image * (f if image.ndim == 2 else f[..., None])).astype(np.float32)


def circle_overlap_area(r1: float, r2: float, d: float) -> float:
    """Area of the intersection of two circles of radii r1, r2 whose centres are d apart."""
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        return math.pi * min(r1, r2) ** 2
    a1 = r1 * r1 * math.acos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
    a2 = r2 * r2 * math.acos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
    k = 0.5 * math.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2))
    return a1 + a2 - k


def clear_fraction(sensor_offset_mm: float, params: Vignetting, aperture_diameter_mm: float,
                   sensor_distance_mm: float, inverse_focus_distance_per_mm: float) -> float:
    """Fraction of the circular pupil whose rays pass the front stop, for a sensor point
    ``sensor_offset_mm`` from the axis (the closed form behind the cat's eye)."""
    L, rad = params.front_stop()
    shrink = 1.0 - L * inverse_focus_distance_per_mm
    centre = sensor_offset_mm * L / sensor_distance_mm / shrink
    a = 0.5 * aperture_diameter_mm
    return circle_overlap_area(a, rad / shrink, centre) / (math.pi * a * a)
