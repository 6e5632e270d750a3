"""The angle of view a calibration gives, with its interval: focus breathing made visible.

A lens that focuses by moving one group (most modern ones) changes its focal length, and with it
the field of view, as it focuses: breathing. The pinhole focal length a calibration measures at
each focus setting (in px) and the image size give each setting's angles of view directly:
horizontal, vertical and diagonal, each the angle between the rays through the image's opposite
edges (or corners) at the calibrated principal point, in the undistorted image. The 95 % interval
maps the focal length's (Student's t where its sigma is a jackknife's, with its degrees of
freedom) through the angle, which falls as the focal length grows.
"""

from __future__ import annotations

import math

from scipy import stats


def _angle_deg(a: tuple[float, float], b: tuple[float, float], f_px: float) -> float:
    """The angle between the rays through image points ``a`` and ``b`` (px from the principal point)."""
    u = (a[0], a[1], f_px)
    v = (b[0], b[1], f_px)
    dot = sum(p * q for p, q in zip(u, v))
    return math.degrees(math.acos(max(-1.0, min(1.0, dot / (math.hypot(*u) * math.hypot(*v))))))


def angles_of_view_deg(f_px: float, shape_px: tuple[int, int], principal_point_px: tuple[float, float]) -> dict:
    """Horizontal, vertical and diagonal angles of view (degrees) of an image ``shape_px`` (height,
    width) with focal length ``f_px`` and principal point ``principal_point_px`` (x, y; pixel
    centres at integers, so the image spans -0.5 to width - 0.5)."""
    h, w = shape_px
    cx, cy = principal_point_px
    left, right, top, bottom = -0.5 - cx, w - 0.5 - cx, -0.5 - cy, h - 0.5 - cy
    return {"horizontal": _angle_deg((left, 0.0), (right, 0.0), f_px),
            "vertical": _angle_deg((0.0, top), (0.0, bottom), f_px),
            "diagonal": _angle_deg((left, top), (right, bottom), f_px)}


def field_of_view(f_px: float, sigma_px: float, dof: float, shape_px: tuple[int, int],
                  principal_point_px: tuple[float, float]) -> dict:
    """Each angle of view (degrees) with its 1 sigma and 95 % interval from the focal length's
    ``sigma_px`` (``dof``: its degrees of freedom; 0 or infinite: Gaussian)."""
    k = float(stats.t.ppf(0.975, dof)) if 0 < dof < math.inf else float(stats.norm.ppf(0.975))
    mid = angles_of_view_deg(f_px, shape_px, principal_point_px)
    wide = angles_of_view_deg(max(f_px - k * sigma_px, 1e-9), shape_px, principal_point_px)
    narrow = angles_of_view_deg(f_px + k * sigma_px, shape_px, principal_point_px)
    step = max(1e-6 * f_px, 1e-9)
    slope = {n: (angles_of_view_deg(f_px - step, shape_px, principal_point_px)[n] - v) / step
             for n, v in mid.items()}
    return {n: {"value": v, "sigma": abs(slope[n]) * sigma_px, "ci95": [narrow[n], wide[n]]} for n, v in mid.items()}
