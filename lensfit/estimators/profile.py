"""The edge profile of the ``edge`` estimator: pixels near a target edge projected on its normal,
the line re-located in the image, binned in strips along the edge with a standard error per bin.

See ``lensfit.estimators.edge`` for the method; this module only gathers the data it fits.
"""

from __future__ import annotations

import numpy as np

from lensfit.estimators.base import EdgeTask

MIN_PIXELS = 24
QUANTISATION_VARIANCE = (1.0 / 65535.0) ** 2 / 12.0
MODEL_FLOOR_INTENSITY = 3e-4
BIN_PX = 1.0 / 8.0  # finest super-sampling of the edge profile (ISO 12233 uses 1/4 px)
#: Bins across the edge at most (a wider window gets wider bins), and strips along it.
NBINS_ACROSS = 128
STRIPS = 2


def select(image: np.ndarray, task: EdgeTask, half_width: float, end_margin: float):
    """Pixels within ``half_width`` of the edge line and at least ``end_margin`` from its ends,
    with the line re-fitted to the image and the profile binned.

    Returns (d, v, se, normal, length, shortened, pixels) or None: ``d`` the mean normal distance
    and ``v`` the mean value of the pixels in each bin (1/8 px, or 1/128 of a wider window; per
    strip along the edge), ``se`` the standard error of that
    mean from the spread within the bin (noise is often heteroscedastic: a render is noisy only
    where the blur mixes two levels, a sensor more where it is bright), floored by the model
    error and quantisation.
    """
    p0, p1 = np.asarray(task.start_px, float), np.asarray(task.end_px, float)
    L = float(np.hypot(*(p1 - p0)))
    t = (p1 - p0) / L
    n = np.array([-t[1], t[0]])
    h, w = image.shape
    lo = np.floor(np.minimum(p0, p1) - half_width - 1).astype(int)
    hi = np.ceil(np.maximum(p0, p1) + half_width + 1).astype(int)
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w - 1), min(hi[1], h - 1)
    if x1 < x0 or y1 < y0:
        return None
    yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    rel_x, rel_y = xx - p0[0], yy - p0[1]
    s = rel_x * t[0] + rel_y * t[1]
    d = rel_x * n[0] + rel_y * n[1]
    margin = min(end_margin, 0.45 * L)
    keep = (np.abs(d) <= half_width) & (s >= margin) & (s <= L - margin)
    if keep.sum() < MIN_PIXELS:
        return None
    s, d, v = s[keep], d[keep], image[y0:y1 + 1, x0:x1 + 1][keep].astype(np.float64)
    line_a, line_b = _edge_line(s, d, v)
    d = d - (line_a + line_b * s)
    # Bin the super-sampled profile in strips along the edge (so that the fit can still turn
    # the line); the bin's mean position keeps the binning exact to first order.
    s_rel = s - 0.5 * L
    strip = np.clip(np.floor((s - s.min()) / max(np.ptp(s), 1e-9) * STRIPS), 0, STRIPS - 1).astype(int)
    # 1/8 px bins, coarser on wide windows (at most NBINS_ACROSS across: a bin is then still
    # under 1/60 of the window, far finer than the spot's structure there).
    bin_px = max(BIN_PX, float(np.ptp(d)) / (NBINS_ACROSS - 2))
    idx = np.floor(d / bin_px).astype(int)
    idx = (idx - idx.min()) * STRIPS + strip
    count = np.bincount(idx)
    used = count > 0
    sum_d = np.bincount(idx, weights=d)[used]
    sum_s = np.bincount(idx, weights=s_rel)[used]
    sum_v = np.bincount(idx, weights=v)[used]
    sum_v2 = np.bincount(idx, weights=v * v)[used]
    count = count[used].astype(np.float64)
    mean_v = sum_v / count
    # Noise variance pooled over 1 px bands across the edge (noise is often heteroscedastic: a
    # render is noisy only where the blur mixes two levels, a sensor more where it is bright);
    # per-bin spreads of a few pixels would make noisy weights and bias the fit.
    sq_dev = np.maximum(sum_v2 - count * mean_v**2, 0.0)
    band = np.floor((sum_d / count) / 1.0).astype(int)
    band -= band.min()
    dof = np.bincount(band, weights=count - 1.0)
    pooled = np.bincount(band, weights=sq_dev) / np.maximum(dof, 1.0)
    overall = sq_dev.sum() / max((count - 1.0).sum(), 1.0)
    spread = np.where(dof[band] >= 3, pooled[band], overall)
    p5, p95 = np.percentile(v, [5.0, 95.0])
    floor = (MODEL_FLOOR_INTENSITY * (p95 - p5)) ** 2 + QUANTISATION_VARIANCE
    se = np.sqrt((spread + floor) / count)
    # The edge line found in the image, before the fitted offset d0: d_pred = a + b s.
    line = (p0 + line_a * n, p0 + L * t + (line_a + line_b * L) * n)
    return sum_d / count, sum_s / count, mean_v, se, n, L, margin < end_margin, int(count.sum()), line


def _edge_line(s: np.ndarray, d: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """Offset of the image's edge from the predicted line, ``a + b s`` (returns a, b).

    In each of a few strips along the edge, the edge sits at the centroid of the profile's
    derivative; a straight line through those centroids corrects small errors of the pose
    (position and angle) before the profile is built.
    """
    if STRIPS < 3:
        # A line through two centroids would not be checked by a third: the fit's own offset and
        # turn (lensfit.estimators.edge) place the line.
        return 0.0, 0.0
    edges = np.linspace(s.min(), s.max() + 1e-9, STRIPS + 1)
    centres, positions = [], []
    for k in range(STRIPS):
        m = (s >= edges[k]) & (s < edges[k + 1])
        if m.sum() < 8:
            continue
        order = np.argsort(d[m])
        dd, vv = d[m][order], v[m][order]
        # Smooth a little, then the centroid of |dv/dd| (robust to the sign of the step).
        k_bins = np.arange(np.floor(dd.min()), np.ceil(dd.max()) + 1.0, 0.5)
        if k_bins.size < 4:
            continue
        prof = np.interp(k_bins, dd, vv)
        grad = np.abs(np.diff(prof))
        if grad.sum() <= 0:
            continue
        mid = 0.5 * (k_bins[1:] + k_bins[:-1])
        centres.append(0.5 * (edges[k] + edges[k + 1]))
        positions.append(float(np.sum(grad * mid) / grad.sum()))
    if len(centres) < 3:
        return 0.0, 0.0
    slope, offset = np.polyfit(centres, positions, 1)
    return float(offset), float(slope)
