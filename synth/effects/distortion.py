"""``distortion``: Brown-Conrady radial and tangential lens distortion.

Model (OpenCV's convention, so OpenCV's calibration recovers the same numbers)
-------------------------------------------------------------------------------
An undistorted (pinhole) image point at normalised coordinates ``(x, y) = ((u - cx)/f_px,
(v - cy)/f_px)``, ``r^2 = x^2 + y^2``, appears at

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

(Brown 1966, "Decentering distortion of lenses"; Conrady 1919). ``f_px = s / p`` is the
calibrated focal length in pixels. The ray tracer distorts exactly: every sample of a pixel
traces the ray of its own undistorted position (``pixel_warp``: the pixel centre's
undistorted position and the local inverse Jacobian). For ``convolve`` the rendered
(undistorted) image is resampled at
the undistorted position of every output pixel (found by Newton iteration of the model, to
1e-9 px) by cubic B-spline interpolation (``scipy.ndimage.map_coordinates``, exact source
positions; OpenCV's ``remap`` rounds them to 1/32 px), clipped to the source's range: so the sensor image is warped after
the optics, as a lens's distortion moves image points without changing their blur. Lateral
chromatic aberration (``synth.effects.chromatic_aberration``) scales each channel about the
principal point in the same resampling, its irradiance divided by the magnification squared
(the channel's light is conserved; distortion itself keeps radiance, as renderers do).

Accuracy: exact for image content blurred over a few pixels (the usual case: defocus); an
edge sharper than a pixel rings by up to about 10 % of its contrast next to the edge (cubic
interpolation of an undersampled step), as any resampling of a rendered image does.

==========================  ======  ================================================
parameter                   unit    meaning
==========================  ======  ================================================
``k1``, ``k2``, ``k3``              radial coefficients (k1 < 0: barrel; > 0: pincushion)
``p1``, ``p2``                      tangential (decentring) coefficients
==========================  ======  ================================================
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

NAME = "distortion"


@dataclass(frozen=True)
class Distortion:
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def opencv(self) -> np.ndarray:
        """(k1, k2, p1, p2, k3): OpenCV's ``distCoeffs`` order."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    def truth(self, focal_length_px: float | None = None, principal_point_px=None) -> dict:
        """Coefficients (and, for an image, the focal length in px and principal point they use)."""
        out = {"model": "Brown-Conrady, OpenCV convention, normalised by focal_length_px",
               "k1": self.k1, "k2": self.k2, "k3": self.k3, "p1": self.p1, "p2": self.p2,
               "opencv_dist_coeffs": self.opencv.tolist()}
        if focal_length_px is not None:
            out.update(focal_length_px=focal_length_px, principal_point_px=list(principal_point_px))
        return out

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted -> distorted coordinates."""
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """Distorted -> undistorted normalised coordinates (Newton with a numerical Jacobian)."""
        x, y = xd.copy(), yd.copy()
        h = 1e-7
        for _ in range(iterations):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x, y + h)
            j11, j21 = (ax - fx) / h, (ay - fy) / h
            j12, j22 = (bx - fx) / h, (by - fy) / h
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (-j21 * ex + j11 * ey) / det
            if max(np.abs(ex).max(), np.abs(ey).max()) < 1e-13:
                break
        return x, y


@functools.lru_cache(maxsize=4)
def undistorted_normalised(width_px: int, height_px: int, focal_length_px: float, principal_point_px,
                           distortion: Distortion | None) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates (x, y) seen at each output pixel centre (cached: every shot
    of a stack shares them; the arrays are read-only)."""
    cx, cy = principal_point_px
    u, v = np.meshgrid(np.arange(width_px, dtype=np.float64), np.arange(height_px, dtype=np.float64))
    x, y = (u - cx) / focal_length_px, (v - cy) / focal_length_px
    x, y = distortion.undistort(x, y) if distortion is not None else (x, y)
    x.flags.writeable = False
    y.flags.writeable = False
    return x, y


def pixel_warp(camera, distortion: Distortion) -> np.ndarray:
    """Per pixel (H, W, 6): the pinhole position (u, v) whose image the distortion moves to the
    pixel centre, and its derivatives (du/dx, du/dy, dv/dx, dv/dy) with respect to the position
    in the distorted pixel (the inverse of the distortion's Jacobian), for the ray tracer."""
    x, y = undistorted_normalised(camera.width_px, camera.height_px, camera.focal_length_px,
                                  camera.principal_point_px, distortion)
    h = 1e-6
    fx0, fy0 = distortion.distort(x - h, y)
    fx1, fy1 = distortion.distort(x + h, y)
    gx0, gy0 = distortion.distort(x, y - h)
    gx1, gy1 = distortion.distort(x, y + h)
    a, c = (fx1 - fx0) / (2 * h), (fy1 - fy0) / (2 * h)  # d(x_d, y_d) / d x
    b, d = (gx1 - gx0) / (2 * h), (gy1 - gy0) / (2 * h)  # d(x_d, y_d) / d y
    det = a * d - b * c
    cx, cy = camera.principal_point_px
    f = camera.focal_length_px
    return np.stack([cx + f * x, cy + f * y, d / det, -b / det, -c / det, a / det], axis=-1)


def warp(image: np.ndarray, camera, distortion: Distortion | None,
         magnifications: tuple[float, ...] | None = None) -> np.ndarray:
    """Resample each channel at its source positions (cubic B-spline; edges replicated)."""
    from scipy.ndimage import map_coordinates

    channels = image[..., None] if image.ndim == 2 else image
    out = np.empty_like(channels, dtype=np.float32)
    x, y = undistorted_normalised(camera.width_px, camera.height_px, camera.focal_length_px,
                                  camera.principal_point_px, distortion)  # once for every channel
    cx, cy = camera.principal_point_px
    for c in range(channels.shape[-1]):
        m = 1.0 if magnifications is None else magnifications[c]
        mx, my = cx + camera.focal_length_px * x / m, cy + camera.focal_length_px * y / m
        src = channels[..., c].astype(np.float64)
        # a magnified channel spreads the same light over m^2 the area
        out[..., c] = np.clip(map_coordinates(src, [my, mx], order=3, mode="nearest"), src.min(), src.max()) / m**2
    return out[..., 0] if image.ndim == 2 else out
