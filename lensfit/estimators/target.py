"""``target``: analysis by synthesis of the known target texture around each edge.

PSF model
    A uniform disk of diameter c (the thin-lens circle of confusion), pixel-integrated.
Method
    The target's printed texture (OpenCV's own ChArUco rendering, the checkerboard or the
    slanted square) is warped into the image through the homography of the calibrated pose,
    averaged over each of 4 x 4 sub-pixels per pixel (4 x 4 samples each), blurred by FFT with
    an area-weighted disk of candidate diameter c (less the variance of one sub-pixel's box,
    which the discretisation adds), averaged back to pixels and compared with the image over the two
    squares beside the edge (markers included: every pixel is modelled, so the window is not
    limited to the clean room). Gain and offset are solved linearly for each c (variable
    projection) and c minimises the residual sum of squares by a bounded scalar search on
    log c (grid, then Brent). Lens distortion is neglected inside the small patch.
Uncertainty
    1 sigma from the curvature of the residual sum of squares at the minimum,
    ``sigma_c^2 = 2 s^2 / RSS''(c)`` with s^2 the residual variance, combined in quadrature with
    the same model floor as ``edge`` (0.3 % of c + 0.02 px); where the RSS is flat at its minimum
    (a blur below a sub-pixel), how far c rises before the RSS rises by s^2. Against synth's
    truth maps (noise-free; tests/measurement/test_measure.py): the calibration stack's 121 edges at 0-5 px,
    error over sigma 1.06 RMS, 93 % within 2 sigma; the demo's 264 at 0-20 px, 1.54 RMS (a few
    near-focus edges), 77 % within 1 sigma, bias +0.005 px from 1.5 px up.
Valid range
    c from about 0.5 px to a few square widths; blur that varies strongly across the patch
    (steep tilt) is averaged.
Cost
    Tens of FFTs per edge: roughly 100-200 times the ``edge`` estimator (lensfit bench-measure).
Reference
    Analysis by synthesis for defocus, e.g. Favaro & Soatto, *3-D Shape Estimation and Image
    Restoration*, Springer 2007, ch. 4.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize
import scipy.signal

from lensfit.estimators.base import BlurEstimate, EdgeTask, Flag, with_model_floor
from lensfit.measurement.psf import disk_kernel

SUB = 4
#: Texture samples per sub-pixel, along each axis (see _measure_one): one sample puts the
#: squares' edges on a 1/SUB px staircase that the fit reads as blur (near-focus edges 0.3 px
#: high on the demo stack); four read 3-20 px blurs within 0.003 px of the truth maps.
POINTS = 4
#: The variance per axis (px^2) taken off the disk for the model's own discretisation, which
#: adds that of one to two boxes of 1/SUB px (the sub-pixels' areas, the area-weighted kernel's
#: cells): one box's. On the demo, the bias from 1.5 px of blur up is +0.003 to +0.005 px with
#: it, -0.016 to -0.001 px with none and +0.007 to +0.025 px with two boxes' (the test's
#: calibration stack was not used to choose).
CELL_VARIANCE_PX2 = 1.0 / (12.0 * SUB * SUB)
MAX_ALONG_PX = 64.0  # patch size caps: enough pixels for a precise fit, bounded cost
MAX_ACROSS_PX = 48.0


def _sample_texture(task: EdgeTask, xs: np.ndarray, ys: np.ndarray) -> np.ndarray | None:
    """Texture (0 dark .. 1 light) at image points, through the inverse homography."""
    ctx = task.context
    target, pose, intr = ctx.get("target"), ctx.get("pose"), ctx.get("intrinsics")
    if target is None or pose is None or intr is None:
        return None
    K = intr.camera_matrix
    H = K @ np.column_stack([pose.R_cam_target[:, 0], pose.R_cam_target[:, 1], pose.t_cam_target_mm])
    Hinv = np.linalg.inv(H)
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    bx, by, bw = Hinv @ pts
    bx, by = bx / bw, by / bw
    spec = target.spec
    if target.kind == "slanted-edge":
        e = float(spec["edge_mm"])
        inside = (bx >= 0) & (bx <= e) & (by >= 0) & (by <= e)
        return np.where(inside, 0.0, 1.0).reshape(xs.shape)
    raster, mm = target.texture()
    ci = np.floor(bx / mm).astype(int)
    ri = np.floor(by / mm).astype(int)
    on = (ci >= 0) & (ci < raster.shape[1]) & (ri >= 0) & (ri < raster.shape[0])
    vals = np.where(on, raster[np.clip(ri, 0, raster.shape[0] - 1), np.clip(ci, 0, raster.shape[1] - 1)], 1.0)
    return vals.reshape(xs.shape)


def _patch(task: EdgeTask, shape):
    """Pixel box and mask: the two squares' width beside the edge, ends trimmed."""
    p0, p1 = np.asarray(task.start_px, float), np.asarray(task.end_px, float)
    L = float(np.hypot(*(p1 - p0)))
    t = (p1 - p0) / L
    n = np.array([-t[1], t[0]])
    across = min(max(task.clear_left_px, task.clear_right_px), 0.4 * L, MAX_ACROSS_PX)
    margin = max(0.15 * L, 0.5 * (L - MAX_ALONG_PX))
    h, w = shape
    corners = np.array([p0 + margin * t + across * n, p0 + margin * t - across * n,
                        p1 - margin * t + across * n, p1 - margin * t - across * n])
    x0, y0 = np.floor(corners.min(axis=0)).astype(int)
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    s = (xx - p0[0]) * t[0] + (yy - p0[1]) * t[1]
    d = (xx - p0[0]) * n[0] + (yy - p0[1]) * n[1]
    mask = (s >= margin) & (s <= L - margin) & (np.abs(d) <= across)
    return (x0, y0, x1, y1), mask


def _measure_one(image: np.ndarray, task: EdgeTask) -> BlurEstimate:
    box = _patch(task, image.shape)
    if box is None:
        return BlurEstimate(None, None, (Flag.TOO_FEW_PIXELS,))
    (x0, y0, x1, y1), mask = box
    data = image[y0:y1 + 1, x0:x1 + 1][mask]
    # Sharp texture on sub-pixels over the box plus a margin for the largest blur considered.
    pad = int(min(0.5 * max(task.clear_left_px, task.clear_right_px), MAX_ACROSS_PX)) + 2
    bx0, by0 = x0 - pad, y0 - pad
    nxp, nyp = (x1 - x0 + 1) + 2 * pad, (y1 - y0 + 1) + 2 * pad
    sub = (np.arange(SUB) + 0.5) / SUB - 0.5
    X, Y = np.meshgrid(((bx0 + np.arange(nxp))[:, None] + sub[None, :]).ravel(),
                       ((by0 + np.arange(nyp))[:, None] + sub[None, :]).ravel())
    # Each sub-pixel the mean of POINTS x POINTS texture samples over it (its area, nearly): one
    # sample at its centre put each square's edge on a 1/SUB px staircase, which read as blur.
    offsets = ((np.arange(POINTS) + 0.5) / POINTS - 0.5) / SUB
    sharp = None
    for oy in offsets:
        for ox in offsets:
            values = _sample_texture(task, X + ox, Y + oy)
            if values is None:
                return BlurEstimate(None, None, (Flag.NO_POSE,))
            sharp = values if sharp is None else sharp + values
    sharp = sharp / POINTS**2
    max_c = 2.0 * (pad - 1)

    def synth(c):
        # The disk drawn is the one whose variance (c^2/16 per axis for diameter c), with the
        # discretisation's (CELL_VARIANCE_PX2), is that of the disk of diameter c.
        k = disk_kernel(SUB * math.sqrt(max(c * c - CELL_VARIANCE_PX2 * 16.0, 0.0)))
        blurred = scipy.signal.fftconvolve(sharp, k, mode="same") if k.size > 1 else sharp
        px = blurred.reshape(nyp, SUB, nxp, SUB).mean(axis=(1, 3))
        return px[pad:pad + (y1 - y0 + 1), pad:pad + (x1 - x0 + 1)][mask]

    def rss(log_c):
        model = synth(math.exp(log_c))
        A = np.column_stack([np.ones_like(model), model])
        coef, *_ = np.linalg.lstsq(A, data, rcond=None)
        r = data - A @ coef
        return float(r @ r)

    grid = np.log(np.geomspace(0.1, max(max_c, 0.2), 14))
    costs = [rss(g) for g in grid]
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    res = scipy.optimize.minimize_scalar(rss, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    c = math.exp(res.x)
    n_pix = data.size
    s2 = res.fun / max(n_pix - 3, 1)
    h = max(0.02 * c, 0.01)
    curvature = (rss(math.log(c + h)) - 2 * res.fun + rss(math.log(max(c - h, 1e-3)))) / (h * h)
    flags = []
    if curvature > 0 and math.isfinite(curvature):
        sigma_fit = math.sqrt(2.0 * s2 / curvature)
    else:  # flat at the minimum (a blur below a sub-pixel): how far c rises before the RSS does
        sigma_fit = _rise(rss, c, res.fun + s2, max_c)
        if sigma_fit is None:
            return BlurEstimate(None, None, (Flag.FLAT_COST,), n_pix)
    sigma = with_model_floor(sigma_fit, c)
    if c >= 0.95 * max_c:
        flags.append(Flag.WINDOW_TRUNCATED)
    return BlurEstimate(c, sigma, tuple(flags), n_pix, math.sqrt(s2))


def _rise(rss, c: float, level: float, max_c: float) -> float | None:
    """How far above ``c`` the residual sum of squares ``rss`` (of log c) first reaches ``level``
    (the minimum plus one residual variance: one sigma's rise for a parabola); None where it
    does not by ``max_c``."""
    if max_c <= c or rss(math.log(max_c)) < level:
        return None
    up = scipy.optimize.brentq(lambda lc: rss(lc) - level, math.log(c), math.log(max_c), xtol=1e-3)
    return math.exp(up) - c


def measure(image: np.ndarray, tasks: list[EdgeTask]) -> list[BlurEstimate]:
    """Blur-disk diameter at each edge by analysis by synthesis (see the module docstring)."""
    image = np.asarray(image, np.float64)
    return [_measure_one(image, t) for t in tasks]
