"""``convolve``: sharp render of each fronto-parallel object, blurred by its exact PSF.

For a plane at depth z parallel to the sensor, the thin lens maps the plane to the sensor by
a pure scale (the chief ray, s/z) and spreads every point into the same uniform disk of
diameter C(z) = A s |1/D_s - 1/z| centred on its chief-ray point. The image of the plane is
therefore the scaled texture convolved with that disk, then integrated over each pixel.

Here the texture (and the object's coverage mask) is averaged over each of ``S x S``
sub-pixels per pixel (exactly for boards, slanted edges and uniform patches, see
``synth.area``; by point sampling at sub-pixel centres for Siemens stars and image files),
convolved by FFT with the disk rasterised at the same resolution (each kernel cell holds the
area of the disk inside it to 1/64, normalised to unit sum), and averaged back over each
pixel's S x S sub-pixels (pixel integration). The error falls like 1/S^2 and with the blur:
about 3e-4 of the contrast at a CoC of 9 px (S = 4), but up to 1e-2 for a CoC near or below
one pixel, where only ray tracing is exact. Objects are
composited back to front: ``I = I (1 - K*a) + K*(a t)``. With a uniform background this is
exact, because the fraction of the aperture whose rays miss an object is ``K*a`` exactly;
it is not exact where the blurred footprints of two objects overlap (partial occlusion of a
textured object), which ``synth.planning.choose_method`` checks.

Cost: one FFT convolution per object over its footprint at S^2 times the pixel count;
independent of the blur size up to the FFT padding.
"""

from __future__ import annotations

import math
import os
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.measurement import psf
from synth import area, textures
from synth.scene import PlacedObject, Shot


def disk_kernel(diameter: float, oversample: int = 8) -> np.ndarray:
    """The area-weighted disk of ``lensfit.measurement.psf.disk_kernel``.

    Convolving cell averages with it is accurate to O(cell^2) for blur of several cells; for a
    blur of about a pixel or less the error near sharp edges reaches 1e-3 to 1e-2 of the contrast
    (measured in tests/synth/test_synth_render.py), which is why ``auto`` ray traces such shots.
    """
    return psf.disk_kernel(diameter, oversample)


@partial(jax.jit, static_argnames=("static",))
def _sample_texture(static, raster, x_mm, y_mm):
    inside = textures.inside(static, x_mm[None, :], y_mm[:, None])
    value = textures.evaluate(static, raster, x_mm[None, :], y_mm[:, None])
    return jnp.where(inside, value, 0.0), inside.astype(jnp.float32)


def footprint_px(obj: PlacedObject, shot: Shot) -> tuple[float, float, float, float]:
    """Pixel bounds (u0, v0, u1, v1) of a fronto-parallel object's sharp image."""
    cam = shot.camera
    cx, cy = cam.principal_point_px
    z = obj.pose.t_cam_target[2]
    k = cam.focal_length_px / z
    ox, oy = obj.pose.t_cam_target[0], obj.pose.t_cam_target[1]
    w, h = obj.target.size_mm
    return (cx + k * (ox - w / 2), cy + k * (oy - h / 2), cx + k * (ox + w / 2), cy + k * (oy + h / 2))


def blurred_footprint_px(obj: PlacedObject, shot: Shot, extent: float = 1.0) -> tuple[float, float, float, float]:
    """``footprint_px`` grown by the blur's reach (``extent`` x the CoC radius) and a pixel."""
    u0, v0, u1, v1 = footprint_px(obj, shot)
    r = 0.5 * extent * float(shot.camera.coc_diameter_px(obj.pose.t_cam_target[2])) + 1.0
    return (u0 - r, v0 - r, u1 + r, v1 + r)


def convolve_bytes(shot: Shot, supersampling: int, *, camera=None) -> float:
    """Peak memory (bytes) ``render_convolve`` needs for one shot: the largest object's blur
    kernel and its FFT grid (objects are convolved one after another), plus the image."""
    cam = camera if camera is not None else shot.camera
    W, H, S = cam.width_px, cam.height_px, int(supersampling)
    peak = 0.0
    for obj in shot.objects:
        coc = float(cam.coc_diameter_px(float(obj.pose.t_cam_target[2])))
        n = 2 * math.ceil(0.5 * coc * S + 0.5) + 1  # kernel side, sub-pixels (lensfit.measurement.psf.disk_kernel)
        reach_px = n // 2 // S + 1
        u0, v0, u1, v1 = footprint_px(obj, shot)
        cols = max(0, min(math.ceil(u1) + 1, W - 1 + reach_px) - max(math.floor(u0) - 1, -reach_px) + 1) * S
        rows = max(0, min(math.ceil(v1) + 1, H - 1 + reach_px) - max(math.floor(v0) - 1, -reach_px) + 1) * S
        fft = float(cols + n) * float(rows + n)
        peak = max(peak, 12.0 * n * n + 40.0 * fft)  # kernel (float64 + float32); 2 images, their spectra
    return peak + 16.0 * W * H


def _convolve_full(planes: tuple[np.ndarray, ...], kernel: np.ndarray) -> list[np.ndarray]:
    """Each of ``planes`` (float32, one shape) convolved with ``kernel`` (float32), the "full"
    result, by FFT on all cores (as ``scipy.signal.fftconvolve``: errors ~1e-6 of full scale, far
    below a 16-bit step), the kernel's transform computed once for all of them."""
    import scipy.fft  # (imported here: a ray-traced stack need not wait for it)

    shape = [n + k - 1 for n, k in zip(planes[0].shape, kernel.shape)]
    fshape = [scipy.fft.next_fast_len(n, True) for n in shape]
    with scipy.fft.set_workers(os.cpu_count() or 1):
        spectrum = scipy.fft.rfft2(kernel, fshape)
        return [scipy.fft.irfft2(scipy.fft.rfft2(p, fshape) * spectrum, fshape)[:shape[0], :shape[1]] for p in planes]


def block_mean(image: np.ndarray, n: int) -> np.ndarray:
    """The means of ``image``'s n x n blocks (its sides multiples of n), float32: OpenCV's area
    resampling, which at a whole factor is that mean (within float32 rounding; 8x numpy's
    reshaped mean on a 13 MP plane)."""
    import cv2

    rows, cols = image.shape[0] // n, image.shape[1] // n
    if n == 1:
        return np.asarray(image, np.float32)
    return cv2.resize(np.ascontiguousarray(image, np.float32), (cols, rows), interpolation=cv2.INTER_AREA)


def render_convolve(shot: Shot, background: float, supersampling: int, *, camera=None,
                    aperture=None, fine: int = 1):
    """Render one shot of fronto-parallel objects; returns linear radiance, float32 (H, W).

    ``camera`` replaces the shot's camera (one colour channel's, under chromatic aberration);
    ``aperture`` (``synth.effects.aperture.Aperture``) replaces the disk PSF by its shape.
    ``fine`` (a factor k above 1 that divides ``supersampling``): returns (image, fine image), the
    fine image at k times the resolution (each cell the mean of its S/k x S/k sub-pixels, objects
    composited there) and the image its k x k means; diffraction filters the fine one.
    """
    cam = camera if camera is not None else shot.camera
    S = int(supersampling)
    R = int(fine)  # output pixels per pixel, along each axis
    if R < 1 or S % R:
        raise ValueError(f"a fine image at {R} times the resolution needs a supersampling divisible by {R}, not {S}")
    SO = S // R  # sub-pixels per output pixel, along each axis
    W, H = cam.width_px * R, cam.height_px * R
    cx, cy = cam.principal_point_px
    image = np.full((H, W), background, np.float64)
    for obj in sorted(shot.objects, key=lambda o: -o.pose.t_cam_target[2]):
        z = float(obj.pose.t_cam_target[2])
        coc = float(cam.coc_diameter_px(z))
        if aperture is None or aperture.shape == "circle":
            kernel = disk_kernel(coc * S)
        else:
            from synth.effects.aperture import kernel as aperture_kernel

            kernel = aperture_kernel(aperture, coc * S)
            if 1.0 / z > cam.inverse_focus_distance_per_mm:
                kernel = kernel[::-1, ::-1]  # in front of the focus plane the spot is the aperture turned 180 deg
        reach = kernel.shape[0] // 2  # in sub-pixels
        reach_px = int(math.ceil(reach / S)) + 1
        u0, v0, u1, v1 = footprint_px(obj, shot)
        # Sharp region: the object's pixels that can blur into the image.
        a0 = max(int(math.floor(u0)) - 1, -reach_px)
        a1 = min(int(math.ceil(u1)) + 1, cam.width_px - 1 + reach_px)
        b0 = max(int(math.floor(v0)) - 1, -reach_px)
        b1 = min(int(math.ceil(v1)) + 1, cam.height_px - 1 + reach_px)
        if a0 > a1 or b0 > b1:
            continue  # entirely outside the view
        mm_per_px = z / cam.focal_length_px
        tex = textures.texture(obj.target)
        # Lower edges of the sub-pixels, in target mm.
        x_lo = (a0 - 0.5 + np.arange((a1 - a0 + 1) * S) / S - cx) * mm_per_px - obj.pose.t_cam_target[0]
        y_lo = (b0 - 0.5 + np.arange((b1 - b0 + 1) * S) / S - cy) * mm_per_px - obj.pose.t_cam_target[1]
        side = mm_per_px / S
        exact = area.area_average(tex.static, tex.raster, x_lo, y_lo, side)
        if exact is not None:
            colour, alpha = exact
        else:  # point-sample at sub-pixel centres (Siemens star, image files)
            colour, alpha = _sample_texture(tex.static, jnp.asarray(tex.raster),
                                            jnp.asarray(x_lo + side / 2, jnp.float32),
                                            jnp.asarray(y_lo + side / 2, jnp.float32))
        colour, alpha = np.asarray(colour, np.float32), np.asarray(alpha, np.float32)
        if kernel.size > 1:
            colour, alpha = _convolve_full((colour, alpha), kernel.astype(np.float32))
            pad = reach
        else:
            pad = 0
        # Sub-pixel grid now starts `pad` sub-pixels before pixel a0's first sub-pixel; align
        # to whole output pixels so that each averages exactly its own SO x SO sub-pixels.
        lead = int(math.ceil(pad / SO)) * SO - pad
        trail_v, trail_u = (-(lead + colour.shape[0])) % SO, (-(lead + colour.shape[1])) % SO
        colour = np.pad(colour, ((lead, trail_v), (lead, trail_u)))
        alpha = np.pad(alpha, ((lead, trail_v), (lead, trail_u)))
        start_u = R * a0 - (pad + lead) // SO
        start_v = R * b0 - (pad + lead) // SO
        nv, nu = colour.shape[0] // SO, colour.shape[1] // SO
        colour, alpha = block_mean(colour, SO), block_mean(alpha, SO)
        # Paste into the image window.
        iu0, iv0 = max(start_u, 0), max(start_v, 0)
        iu1, iv1 = min(start_u + nu, W), min(start_v + nv, H)
        if iu0 >= iu1 or iv0 >= iv1:
            continue
        c = colour[iv0 - start_v:iv1 - start_v, iu0 - start_u:iu1 - start_u]
        a = np.clip(alpha[iv0 - start_v:iv1 - start_v, iu0 - start_u:iu1 - start_u], 0.0, 1.0)
        window = image[iv0:iv1, iu0:iu1]
        image[iv0:iv1, iu0:iu1] = window * (1.0 - a) + c
    if R > 1:
        coarse = image.reshape(cam.height_px, R, cam.width_px, R).mean(axis=(1, 3))
        return coarse.astype(np.float32), image.astype(np.float32)
    return image.astype(np.float32)

