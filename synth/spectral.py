"""Spectral rendering through a compound lens: glass dispersion makes each wavelength focus and
magnify differently (longitudinal and lateral chromatic aberration come out of the trace).

A scene asks for it with ``[lens] wavelengths_nm = [...]`` (a compound lens whose glasses have a
dispersion: ``glass`` or ``V`` in its table, see ``synth.lens``). Each wavelength is ray traced
with the same stop and sensor (the f-number is set at the d line, 587.56 nm, the wavelength the
table's indices are given at; the sensor at the best focus of all wavelengths together, the
grey image's); the stored image is

* grey (the default): the plain mean over the wavelengths, a sensor with a flat response
  seeing a flat (equal-energy) spectrum at those samples;
* colour (``[lens] colour = true``, or when an effect asks for three channels): red, green and
  blue, each the mean over the wavelengths weighted by a Gaussian channel sensitivity centred
  on 610, 550 and 465 nm with a 40 nm standard deviation, a stand-in for a camera's response
  (every channel needs a wavelength within about 85 nm of its centre).

Cost: one ray-traced render per wavelength (``synth plan`` shows it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from synth.effects.diffraction import DEFAULT_RGB_NM

#: Centres of the red, green and blue channel sensitivities (nm) and their standard deviation.
CHANNEL_CENTRES_NM = tuple(float(w) for w in DEFAULT_RGB_NM)
CHANNEL_SIGMA_NM = 40.0
#: A channel needs a wavelength where its sensitivity is at least this (about 2.1 sigma away).
MIN_CHANNEL_SENSITIVITY = 0.1
#: Visible range accepted for ``wavelengths_nm`` (the glass equations hold from 370 nm).
WAVELENGTH_RANGE_NM = (380.0, 780.0)
#: The off-axis point whose image height records lateral colour: this fraction of the image
#: half-diagonal.
LATERAL_FIELD_FRACTION = 0.7


def sensitivity(wavelength_nm) -> np.ndarray:
    """Channel sensitivities (3, n) at the wavelengths (peak 1)."""
    w = np.atleast_1d(np.asarray(wavelength_nm, np.float64))
    mu = np.asarray(CHANNEL_CENTRES_NM)[:, None]
    return np.exp(-0.5 * ((w[None, :] - mu) / CHANNEL_SIGMA_NM) ** 2)


def channel_weights(wavelength_nm) -> np.ndarray:
    """(3, n) weights, each row summing to 1: channel c = sum_k w[c, k] * image at wavelength k."""
    s = sensitivity(wavelength_nm)
    return s / s.sum(axis=1, keepdims=True)


def uncovered_channel(wavelength_nm) -> str | None:
    """The first channel no wavelength excites enough (:data:`MIN_CHANNEL_SENSITIVITY`), or None."""
    s = sensitivity(wavelength_nm)
    for name, centre, row in zip(("red", "green", "blue"), CHANNEL_CENTRES_NM, s):
        if row.max() < MIN_CHANNEL_SENSITIVITY:
            return f"{name} ({centre:g} nm)"
    return None


def combine(planes: list[np.ndarray], wavelength_nm, channels: int) -> np.ndarray:
    """The stored image from the per-wavelength renders: their mean (1 channel) or the weighted
    red, green, blue planes (H, W, 3)."""
    stack = np.stack(planes, axis=-1).astype(np.float64)
    if channels == 1:
        return stack.mean(axis=-1).astype(np.float32)
    return np.einsum("hwk,ck->hwc", stack, channel_weights(wavelength_nm)).astype(np.float32)


def spot_centroid_mm(rx, object_point_mm, pupil_z_mm: float, pupil_radius_mm: float, sensor_z_mm: float,
                     grid: int = 101) -> tuple[float, float, int]:
    """Centroid (x, y) on the plane ``sensor_z_mm`` of the real rays from ``object_point_mm``
    (lens coordinates) that pass ``rx``, aimed over a square grid on the plane ``pupil_z_mm``
    out to ``pupil_radius_mm`` (overfilled: the apertures decide what passes); and how many passed."""
    from synth.lens import disk_grid, trace

    u, v = disk_grid(grid)
    px, py = pupil_radius_mm * u, pupil_radius_mm * v
    ox, oy, oz = (float(c) for c in object_point_mm)
    ddx, ddy, ddz = px - ox, py - oy, np.full_like(px, pupil_z_mm - oz)
    norm = np.sqrt(ddx**2 + ddy**2 + ddz**2)
    origin = (np.full_like(px, ox), np.full_like(px, oy), np.full_like(px, oz))
    (x, y, z), (dx, dy, dz), passed, _ = trace(rx, origin, (ddx / norm, ddy / norm, ddz / norm))
    ok = passed & (dz > 1e-9)
    if ok.sum() == 0:
        return math.nan, math.nan, 0
    t = (sensor_z_mm - z[ok]) / dz[ok]
    return float(np.mean(x[ok] + t * dx[ok])), float(np.mean(y[ok] + t * dy[ok])), int(ok.sum())


def spectral_truth(camera) -> dict[str, Any]:
    """Ground truth of a spectral compound-lens camera (``synth.geometry.CompoundLensCamera``
    with ``wavelengths_nm``), per wavelength; see the keys' descriptions in truth.schema.json."""
    from synth.lens import D_LINE_NM, best_focus_image_z, object_z, paraxial

    ref = camera
    z_obj = ref.scene_origin_z_mm - ref.focus_distance_mm if math.isfinite(ref.focus_distance_mm) else -math.inf
    half_diag_mm = 0.5 * ref.pixel_pitch_mm * math.hypot(ref.width_px, ref.height_px)
    field_mm = LATERAL_FIELD_FRACTION * half_diag_mm
    # The off-axis point: at the focus distance (or 1000 focal lengths for focus at infinity),
    # where a pinhole at the entrance pupil would image it at field_mm.
    depth = ref.focus_distance_mm if math.isfinite(ref.focus_distance_mm) else 1000.0 * ref.focal_length_mm
    point = (field_mm * depth / ref.sensor_distance_mm, 0.0, ref.scene_origin_z_mm - depth)
    pupil_r = 0.75 * ref.paraxial.entrance_pupil_diameter_mm + 0.1 * ref.focal_length_mm

    def height(rx) -> float:  # in the stored image, which is re-inverted: object +x is image +x
        x, _, n = spot_centroid_mm(rx, point, ref.scene_origin_z_mm, pupil_r, ref.sensor_z_mm)
        return -x / ref.pixel_pitch_mm if n >= 16 else math.nan

    h_ref = height(ref.stopped)
    out: dict[str, list] = {k: [] for k in ("efl_mm", "best_focus_image_z_mm", "focus_shift_mm",
                                            "paraxial_in_focus_distance_mm", "image_height_px",
                                            "lateral_colour_px")}
    for cam in ref.spectral_cameras():
        rx = cam.stopped
        out["efl_mm"].append(paraxial(rx).efl_mm)
        bf = best_focus_image_z(rx, z_obj)
        out["best_focus_image_z_mm"].append(bf)
        out["focus_shift_mm"].append(bf - ref.sensor_z_mm)
        d = ref.scene_origin_z_mm - object_z(rx, ref.sensor_z_mm)
        out["paraxial_in_focus_distance_mm"].append(d if math.isfinite(d) and d > 0 else None)
        h = height(rx)
        out["image_height_px"].append(h if math.isfinite(h) else None)
        out["lateral_colour_px"].append(h - h_ref if math.isfinite(h) and math.isfinite(h_ref) else None)
    return {"wavelengths_nm": [float(w) for w in ref.wavelengths_nm], "reference_wavelength_nm": D_LINE_NM,
            "lateral_field_height_px": field_mm / ref.pixel_pitch_mm, **out,
            "channel_centres_nm": list(CHANNEL_CENTRES_NM), "channel_sigma_nm": CHANNEL_SIGMA_NM}
