"""``diffraction``: the Airy pattern of the circular aperture, convolved with the image.

Model
-----
Fraunhofer diffraction at a circular pupil gives the Airy intensity pattern on the sensor

    I(r) = [2 J1(x) / x]^2,   x = pi r / (lambda N_w),

with its first dark ring at ``r = 1.22 lambda N_w``. ``N_w = s / A`` is the working
(image-side) f-number: the sensor sits at ``s``, not ``f``, so a lens focused closer
diffracts more (``N_w = N`` at infinity focus; ``2 N`` at 1:1 macro). Diffraction and defocus
act one after the other on the wave, and for blur of more than a few Airy radii the
geometric spot convolved with the Airy pattern is the standard approximation (Hopkins 1955;
Goodman, *Introduction to Fourier Optics*, 3rd ed., sec. 6.4); near focus it is exact.

==================  ======  ===================================================  ==========
parameter           unit    meaning                                              default
==================  ======  ===================================================  ==========
``wavelength_nm``   nm      one wavelength, or [red, green, blue] when colour    550, or
                            is rendered                                          [610, 550, 465]
==================  ======  ===================================================  ==========

Diffraction acts on the irradiance before the pixels integrate it. So the geometric render is
taken at k = 4 times the resolution, 8 under an Airy pattern smaller than half a pixel, as far
as the samples allow (each cell integrated over its own area;
``synth.effects.stages.fine_choice``), the transfer function of a circular pupil (incoherent
light; Goodman sec. 6.3)::

    OTF(nu) = (2/pi) (acos(v) - v sqrt(1 - v^2)),   v = nu lambda N_w <= 1, 0 beyond,

is multiplied into that image's 2-D FFT (scipy; edges extended by 12 dark rings, 99.2 % of the
energy, to keep the wrap-around out), and each pixel is the mean of its k x k cells. The finer
render costs no extra rays: the ray tracer's n x n strata per pixel fall n/k x n/k into each
cell (``synth.raytrace.cell_factor``: up to 4 at 16 spp, one stratum a cell, whose sample is
uniform within it, so the cell's mean is unbiased; up to 8 at 64 and 256 spp), and the
convolution renderer averages its S x S sub-pixels per cell instead of per pixel (up to 4 at the
default supersampling of 4, 8 at 8). What this leaves out is the cells' own content above
their Nyquist frequency (k/2 cycles per pixel), which folds down where the pupil passes it (up
to ``1 / a`` cycles per pixel, ``a = lambda N_w / p``), attenuated by the cell's own footprint.
It matters where a blur is far below the Airy pattern: read through the Airy model, such a blur
hangs on the profile's width to a few thousandths of a px^2. On an axis-aligned edge blurred by
a 0.28 px disk at ``a = 1.1`` px (cells integrated exactly, read by the edge estimator at four
sub-pixel phases) k = 2 reads 0.0-0.63 px by the phase, k = 4 0.25-0.30 and k = 8 0.276-0.277
(the exact image: 0.276-0.278); under a pattern of ``a = 0.22`` px, k = 4 still reads 0.0-0.36
px for 0.29, k = 8 0.28-0.32, hence 8 there (tests/measurement/test_diffraction.py renders such an edge).
Against the exact transfer-function product (disk x pupil x pixel) an edge at the focus plane at
f/11 on 5 um pixels misfits by 0.15-0.16 % of the contrast RMS, ray traced or convolved. The
finer grid costs the filtering memory and time in proportion to k^2
(``synth.effects.stages.fine_choice`` takes a smaller k where the larger one is beyond the
memory budget).

Where no finer render is to be had (Mitsuba's images, an odd number of samples per pixel or an
odd supersampling, or a finer FFT beyond the memory budget) the transfer function is applied to
the image as sampled, and the truth's ``applied`` says so. That is an approximation: the
pixel-integrated irradiance's content above half a cycle per pixel has already folded down
(aliased) and is attenuated at the folded frequency instead of its own, an error largest where
the images are sharpest (on ``scenes/stopped_down.toml`` the fit's N reads 0.2-0.4 % off at
f/11-f/22 from such images). A pixel-cell-averaged Airy kernel would add a second pixel
footprint on top of the pattern. The aperture is taken as
circular (a polygon's diffraction spikes are not modelled).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

NAME = "diffraction"
DEFAULT_WAVELENGTH_NM = 550.0
DEFAULT_RGB_NM = (610.0, 550.0, 465.0)
#: First zeros of J1 (x = pi r / (lambda N)); ring k is at x = J1_ZEROS[k - 1].
J1_ZEROS = (3.8317, 7.0156, 10.1735, 13.3237, 16.4706, 19.6159, 22.7601, 25.9037, 29.0468, 32.1897,
            35.3323, 38.4748)


@dataclass(frozen=True)
class Diffraction:
    wavelength_nm: tuple[float, ...] = (DEFAULT_WAVELENGTH_NM,)
    reach_rings: int = 12

    def truth(self, working_f_number: float, pixel_pitch_mm: float) -> dict:
        return {"model": "Airy pattern of a circular pupil at the working f-number s/A, convolved with the image",
                "wavelength_nm": list(self.wavelength_nm), "working_f_number": working_f_number,
                "first_dark_ring_radius_px": [first_zero_radius_mm(w, working_f_number) / pixel_pitch_mm
                                              for w in self.wavelength_nm]}


def first_zero_radius_mm(wavelength_nm: float, working_f_number: float) -> float:
    """Radius of the first dark ring on the sensor: ``1.22 lambda N_w`` (mm)."""
    return J1_ZEROS[0] / math.pi * wavelength_nm * 1e-6 * working_f_number


def bytes_needed(params: Diffraction, working_f_number: float, pixel_pitch_mm: float, width_px: int,
                 height_px: int) -> float:
    """Peak memory (bytes) of :func:`apply` for one channel: the padded image, its spectrum, the
    frequency grid and the transfer function."""
    reach_mm = J1_ZEROS[params.reach_rings - 1] / math.pi * max(params.wavelength_nm) * 1e-6 * working_f_number
    half = max(1, math.ceil(reach_mm / pixel_pitch_mm))
    return 40.0 * (width_px + 2 * half + 64) * (height_px + 2 * half + 64)


def otf(nu_cycles_per_px: np.ndarray, wavelength_nm: float, working_f_number: float,
        pixel_pitch_mm: float) -> np.ndarray:
    """Diffraction OTF of a circular pupil at spatial frequency ``nu`` (cycles per pixel), in
    ``nu``'s precision (float32 or float64)."""
    nu = np.asarray(nu_cycles_per_px)
    v = np.abs(nu) * nu.dtype.type(wavelength_nm * 1e-6 * working_f_number / pixel_pitch_mm)
    vc = np.minimum(v, 1.0)
    return np.where(v < 1.0, (2.0 / np.pi) * (np.arccos(vc) - vc * np.sqrt(1.0 - vc * vc)), 0.0).astype(v.dtype)


def apply(image: np.ndarray, params: Diffraction, working_f_number: float, pixel_pitch_mm: float) -> np.ndarray:
    """Filter each channel of ``image`` (H, W) or (H, W, C) by its wavelength's diffraction OTF.

    In float32 (errors ~1e-6 of full scale, far below a 16-bit step), on all cores; the frame is
    extended by the longest wavelength's reach and padded to a fast FFT size, so that channels
    holding the same plane (one geometric render seen at three wavelengths) share one forward
    transform."""
    import scipy.fft

    channels = image[..., None] if image.ndim == 2 else image
    waves = params.wavelength_nm
    if len(waves) not in (1, channels.shape[-1]):
        raise ValueError(f"{len(waves)} wavelengths for {channels.shape[-1]} channels")
    H, W = channels.shape[:2]
    reach_mm = J1_ZEROS[params.reach_rings - 1] / math.pi * max(waves) * 1e-6 * working_f_number
    h = max(1, int(math.ceil(reach_mm / pixel_pitch_mm)))
    ny, nx = scipy.fft.next_fast_len(H + 2 * h, real=True), scipy.fft.next_fast_len(W + 2 * h, real=True)
    out = np.empty(channels.shape, np.float32)
    spectrum, source = None, None
    with scipy.fft.set_workers(os.cpu_count() or 1):
        for c in range(channels.shape[-1]):
            plane = channels[..., c]
            if spectrum is None or not np.array_equal(plane, source):
                padded = np.pad(plane.astype(np.float32), ((h, ny - H - h), (h, nx - W - h)), mode="edge")
                spectrum, source = scipy.fft.rfft2(padded), plane
            wave = waves[c] if len(waves) > 1 else waves[0]
            transfer = _transfer(ny, nx, float(wave), float(working_f_number), float(pixel_pitch_mm))
            out[..., c] = scipy.fft.irfft2(spectrum * transfer, s=(ny, nx))[h:h + H, h:h + W]
    return out[..., 0] if image.ndim == 2 else out


#: The truth's ``applied`` entry: how the transfer function met the image.
def applied_fine(factor: int) -> str:
    """The truth's ``applied`` where the transfer function met the geometric render at ``factor``
    times the resolution."""
    times = "twice" if factor == 2 else f"{factor} times"
    return f"to the irradiance at {times} the resolution, then integrated over each pixel ({factor} x {factor} means)"

APPLIED_SAMPLED = "to the image as sampled (pixel-integrated; an approximation where the image is sharp)"


@lru_cache(maxsize=4)
def _transfer(ny: int, nx: int, wavelength_nm: float, working_f_number: float, pixel_pitch_mm: float) -> np.ndarray:
    """:func:`otf` on the float32 frequency grid of a (ny, nx) real FFT: the same for every shot of
    a stack at one aperture (kept: 20-30 ms a shot of a diffraction render, a tenth of its
    filtering). Read-only."""
    import scipy.fft

    nu = np.hypot(scipy.fft.fftfreq(ny).astype(np.float32)[:, None], scipy.fft.rfftfreq(nx).astype(np.float32)[None, :])
    out = otf(nu, wavelength_nm, working_f_number, pixel_pitch_mm)
    out.flags.writeable = False
    return out


def apply_fine(fine: np.ndarray, params: Diffraction, working_f_number: float, pixel_pitch_mm: float,
               factor: int = 2) -> np.ndarray:
    """The image (H, W) or (H, W, C), float32, from its geometric render at ``factor`` times the
    resolution ``fine`` (kH, kW[, C]): filtered there by each wavelength's transfer function
    (pitch ``pixel_pitch_mm / k``), then each pixel the mean of its k x k cells.

    Done in the frequency domain, where the filtered image holds nothing beyond the pupil's
    cut-off ``1 / a`` cycles per pixel: the fine image's spectrum is cut to the band of a grid m
    times the pixels' (the least m whose Nyquist frequency m/2 exceeds ``1 / a``, at most k; m = 1
    from ``a`` = 2 px), multiplied by the transfer function, the k cells' mean (``sin(pi nu)
    / (k sin(pi nu / k))``) and the half cell that takes the cells' centres to the pixel's, and
    transformed back at that size. The same image as filtering the fine one and averaging its
    cells (within float32 rounding; tests/measurement/test_diffraction.py), with one transform of the fine
    image's size instead of two a channel (about half the time)."""
    import scipy.fft

    k = int(factor)
    channels = fine[..., None] if fine.ndim == 2 else fine
    waves = params.wavelength_nm
    if len(waves) not in (1, channels.shape[-1]):
        raise ValueError(f"{len(waves)} wavelengths for {channels.shape[-1]} channels")
    H, W = channels.shape[0] // k, channels.shape[1] // k
    reach_mm = J1_ZEROS[params.reach_rings - 1] / math.pi * max(waves) * 1e-6 * working_f_number
    h = max(1, int(math.ceil(reach_mm / pixel_pitch_mm)))  # the margin, in pixels
    band = pixel_pitch_mm / (min(waves) * 1e-6 * working_f_number)  # the cut-off, cycles per pixel
    m = min(k, math.floor(2.0 * band) + 1)
    py, px = scipy.fft.next_fast_len(H + 2 * h, real=True), scipy.fft.next_fast_len(W + 2 * h, real=True)
    ny, nx, cy, cx = k * py, k * px, m * py, m * px
    rows = np.r_[0:(cy + 1) // 2, ny - cy // 2:ny]
    out = np.empty((H, W, channels.shape[-1]), np.float32)
    spectrum, source = None, None
    with scipy.fft.set_workers(os.cpu_count() or 1):
        for c in range(channels.shape[-1]):
            plane = channels[..., c]
            if spectrum is None or not np.array_equal(plane, source):
                padded = np.pad(plane.astype(np.float32), ((k * h, ny - k * (H + h)), (k * h, nx - k * (W + h))),
                                mode="edge")
                spectrum, source = scipy.fft.rfft2(padded)[rows, :cx // 2 + 1], plane
            wave = waves[c] if len(waves) > 1 else waves[0]
            transfer = _band_transfer(py, px, k, m, float(wave), float(working_f_number), float(pixel_pitch_mm))
            coarse = scipy.fft.irfft2(spectrum * transfer, s=(cy, cx))
            out[..., c] = coarse[m * h:m * (h + H):m, m * h:m * (h + W):m]
    return out[..., 0] if fine.ndim == 2 else out


@lru_cache(maxsize=6)
def _band_transfer(py: int, px: int, k: int, m: int, wavelength_nm: float, working_f_number: float,
                   pixel_pitch_mm: float) -> np.ndarray:
    """What :func:`apply_fine` multiplies the band of a fine spectrum by (padded frame ``py`` x
    ``px`` pixels, ``k`` cells a pixel, a grid of ``m``): the transfer function, the k cells' mean
    with the half cell that takes their centres to the pixel's, and the two transforms' scale;
    complex64, read-only, kept for the other shots of a stack (a 12-shot camera-raw stack spent
    4.6 s of its 26 computing it for each)."""
    import scipy.fft

    cy, cx = m * py, m * px
    nu_y = (scipy.fft.fftfreq(cy) * m).astype(np.float32)[:, None]
    nu_x = (scipy.fft.rfftfreq(cx) * m).astype(np.float32)[None, :]
    shift = 0.5 - 0.5 / k  # px: the cells' centres (p - 1/2 + (i + 1/2)/k) to the pixel's

    def mean_of_cells(nu):
        zero = nu == 0
        mean = np.where(zero, 1.0, np.sin(np.pi * nu) / (k * np.sin(np.pi * nu / k) + zero))
        return (mean * np.exp(2j * np.pi * shift * nu)).astype(np.complex64)

    out = (otf(np.hypot(nu_y, nu_x), wavelength_nm, working_f_number, pixel_pitch_mm)
           * mean_of_cells(nu_y) * mean_of_cells(nu_x) * np.float32((m / k) ** 2))
    out.flags.writeable = False
    return out


def seconds(width_px: int, height_px: int, channels: int) -> float:
    """Rough cost on 2 cores (FFT convolution of the frame; measured ~0.09 s for 1 MP x 3 channels;
    give it the fine render's pixels where there is one)."""
    return 3e-8 * width_px * height_px * channels + 0.005
