"""The edge profile of the ``edge`` estimator: pixels near a target edge projected on its normal,
the line re-located in the image, binned in strips along the edge with a standard error per bin.

See ``lensfit.estimators.edge`` for the method; this module only gathers the data it fits.
"""

from __future__ import annotations

import math

import numpy as np

from lensfit.estimators.base import EdgeTask

MIN_PIXELS = 24
QUANTISATION_VARIANCE = (1.0 / 65535.0) ** 2 / 12.0
MODEL_FLOOR_INTENSITY = 3e-4
BIN_PX = 1.0 / 8.0  # finest super-sampling of the edge profile (ISO 12233 uses 1/4 px)
#: Bins across the edge at most (a wider window gets wider bins), and strips along it.
NBINS_ACROSS = 128
STRIPS = 2


def select(image: np.ndarray, task: EdgeTask, half_width: float | tuple[float, float], end_margin: float,
           expected: tuple[float, float] | None = None):
    """Pixels within ``half_width`` of the edge line (a pair: right and left of it, the sides of
    negative and positive normal distance) and at least ``end_margin`` from its ends,
    with the line re-fitted to the image and the profile binned.

    Returns (d, s, v, se, normal, length, shortened, pixels, line, se_banded, footprint) or None: ``d`` the
    mean normal distance and ``v`` the mean value of the pixels in each bin (1/8 px, or 1/128
    of a wider window; per strip along the edge), ``se`` the standard error of that mean: its pixel count and the noise
    variance where the bin lies, floored by the model error and quantisation. That variance is
    never the bin's own spread (see :func:`_noise_variance`): with ``expected`` = (offset px,
    disk radius px) of a previous fit to this edge, a smooth function of the profile's expected
    level; without, pooled over each side of the edge. ``se_banded``: the same from the spread
    pooled over 1 px bands (:func:`_band_variance`), for the two-disk fit. ``footprint``: the
    widths of the two boxes the fits convolve the blur with (:func:`footprint`): the pixel's,
    seen along the normal, and the spread of the pixels' positions within their bins.
    """
    p0, p1 = np.asarray(task.start_px, float), np.asarray(task.end_px, float)
    L = float(np.hypot(*(p1 - p0)))
    t = (p1 - p0) / L
    n = np.array([-t[1], t[0]])
    h, w = image.shape
    if isinstance(half_width, tuple):
        half_neg, half_pos = half_width
    else:
        half_neg = half_pos = half_width
    reach = max(half_neg, half_pos)
    lo = np.floor(np.minimum(p0, p1) - reach - 1).astype(int)
    hi = np.ceil(np.maximum(p0, p1) + reach + 1).astype(int)
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w - 1), min(hi[1], h - 1)
    if x1 < x0 or y1 < y0:
        return None
    rel_x = (np.arange(x0, x1 + 1) - p0[0])[None, :]  # broadcast over the box: no index grids
    rel_y = (np.arange(y0, y1 + 1) - p0[1])[:, None]
    s = rel_x * t[0] + rel_y * t[1]
    d = rel_x * n[0] + rel_y * n[1]
    margin = min(end_margin, 0.45 * L)
    keep = (d <= half_pos) & (d >= -half_neg) & (s >= margin) & (s <= L - margin)
    if keep.sum() < MIN_PIXELS:
        return None
    s, d, v = s[keep], d[keep], image[y0:y1 + 1, x0:x1 + 1][keep].astype(np.float64, copy=False)
    line_a, line_b = _edge_line(s, d, v)
    d = d - (line_a + line_b * s)
    # Bin the super-sampled profile in strips along the edge (so that the fit can still turn
    # the line); the bin's mean position keeps the binning exact to first order.
    s_rel = s - 0.5 * L
    strip = np.minimum(((s - s.min()) / max(np.ptp(s), 1e-9) * STRIPS).astype(int), STRIPS - 1)  # (>= 0: floor)
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
    sum_d2 = np.bincount(idx, weights=d * d)[used]
    count = count[used].astype(np.float64)
    mean_v = sum_v / count
    sq_dev = np.maximum(sum_v2 - count * mean_v**2, 0.0)
    spread = _noise_variance(sum_d / count, sq_dev, count, expected)
    banded = _band_variance(sum_d / count, sq_dev, count)
    p5, p95 = _percentiles(v, 5.0, 95.0)
    floor = (MODEL_FLOOR_INTENSITY * (p95 - p5)) ** 2 + QUANTISATION_VARIANCE
    se = np.sqrt((spread + floor) / count)
    se_banded = np.sqrt((banded + floor) / count)
    # The edge line found in the image, before the fitted offset d0: d_pred = a + b s.
    line = (p0 + line_a * n, p0 + L * t + (line_a + line_b * L) * n)
    within = max(float(np.sum(sum_d2 - sum_d * sum_d / count)), 0.0) / float(count.sum())
    return (sum_d / count, sum_s / count, mean_v, se, n, L, margin < end_margin, int(count.sum()), line,
            se_banded, footprint(n, within))


def footprint(normal: np.ndarray, bin_variance_px2: float) -> np.ndarray:
    """The two box widths (px) that the edge fits' model convolves the blur with
    (``lensfit.measurement.psf.pixel_edge_profile``, ``lensfit.measurement.diffraction.edge_kernel``): a unit square
    pixel seen along the edge ``normal`` is two boxes, ``|nx|`` and ``|ny|`` wide; the narrower
    is widened so that the footprint's variance also holds ``bin_variance_px2``, the variance of
    the pixels' normal distances about their bin's mean (pooled over the bins).

    A bin's mean value is the profile averaged over its pixels' positions, which the fit takes
    at their mean: to second order the profile convolved with their spread, a box of 1/8 px on a
    slanted edge (variance 1/768 px^2). Left out, it read the blur of exact edges (a half-plane
    blurred by a uniform disk, integrated over square pixels) too wide by about 0.9 % / c^2 for
    a blur diameter of c px: +0.9 % at 1 px, +0.2 % at 2 px (``lensfit bench-measure``, its
    exact-edge table; tests/measurement/test_measure.py)."""
    a = max(abs(float(normal[0])), abs(float(normal[1])))
    b = min(abs(float(normal[0])), abs(float(normal[1])))
    return np.array([a, math.sqrt(b * b + 12.0 * bin_variance_px2)])


def _percentiles(v: np.ndarray, *qs: float) -> list[float]:
    """``np.percentile(v, qs)`` (linear interpolation between order statistics), by one partial
    sort: numpy's own call costs about 0.15 ms of overhead, paid twice per edge."""
    n = v.size
    pos = [q / 100.0 * (n - 1) for q in qs]
    lows = [min(int(np.floor(p)), n - 1) for p in pos]
    part = np.partition(v, sorted({k for lo in lows for k in (lo, min(lo + 1, n - 1))}))
    return [float(part[lo] + (p - lo) * (part[min(lo + 1, n - 1)] - part[lo])) for p, lo in zip(pos, lows)]


def _noise_variance(d: np.ndarray, sq_dev: np.ndarray, count: np.ndarray,
                    expected: tuple[float, float] | None) -> np.ndarray:
    """The noise variance of one pixel at each bin (``d`` its mean position, ``sq_dev`` the sum
    of squared deviations of its ``count`` pixels from their mean).

    Not the bin's own spread, nor one pooled over a 1 px band (as before): where the noise grows
    with the deviation of the mean (Monte-Carlo noise of a render, where a pixel sees the other
    side of the edge through a few aperture samples; photon noise at low counts), a band that
    came out further from its level, as if the blur were wider there, came out noisier too, took
    less weight, and the blur read low: on 32-spp renders of 1-3 px blurs by 1-1.5 %, which took
    N 1.6 % high with a 95 % interval that excluded the truth (synth's and Mitsuba's renders
    alike). Instead the variance is a function of where the bin lies, fitted to all
    bins at once: with ``expected`` (offset and radius of an earlier disk fit), a quadratic in
    the expected level ``m`` in [0, 1] (``a + b m + c m^2``: read noise, photon noise, and the
    ``m (1 - m)`` of Monte-Carlo noise), never below the variance pooled over the bin's side of
    the edge, so that the weights keep the noise's shape across the edge but depend on no bin's
    own deviation; without ``expected`` (the first pass) that side's variance alone. Measured on
    24 Mitsuba stacks at 32 spp (lensfit bench --suite independent): N's bias +0.14..0.20 % -> +0.04..0.08 %.
    """
    dof = count - 1.0
    by_side = _pooled((d >= 0.0).astype(int), sq_dev, dof)
    if expected is None or not np.all(np.isfinite(expected)) or int(np.sum(dof > 0)) < 12:
        return by_side
    d0, radius = expected
    # the disk's edge-spread function, widened by the pixel's footprint (variance 1/12 px^2
    # against R^2 / 4 for the disk): the level the profile is expected to have at each bin
    r_eff = math.sqrt(radius * radius + 1.0 / 3.0)
    x = np.clip((d - d0) / r_eff, -1.0, 1.0)
    m = 0.5 + (x * np.sqrt(1.0 - x * x) + np.arcsin(x)) / np.pi
    basis = np.stack([np.ones_like(m), m, m * m], axis=1)
    wts = np.sqrt(np.maximum(dof, 0.0))
    per_bin = sq_dev / np.maximum(dof, 1.0)
    coef, *_ = np.linalg.lstsq(basis * wts[:, None], per_bin * wts, rcond=None)
    model = basis @ coef
    if not np.all(np.isfinite(model)):
        return by_side
    # never below the side's mean: a quadratic that dips towards 0 at the flat ends would give
    # bins there weights far beyond what their few pixels justify
    return np.maximum(model, by_side)


def _band_variance(d: np.ndarray, sq_dev: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The spread pooled over 1 px bands across the edge (the weights before
    :func:`_noise_variance`), kept for the two-disk fit of a visibly shaped spot: its faint halo
    shows in the profile's tails, which these weights favour (noise-free, the spread of a bin is
    mostly the profile's slope across it); with the smooth weights the shaped reading of a
    retrofocus lens's core-and-halo spot came out 2.6 % low (``tests/synth/test_compound_render.py``).
    On exact 2-6 px disks under a render's Monte-Carlo noise (32 spp) the shaped readings stay
    within 0.2 % (0.4 % low at 2 px); in the uniform disk's fit these weights would read 1-3 px
    blurs 1-1.5 % low, which is why that fit takes :func:`_noise_variance`'s."""
    band = np.floor(d).astype(int)
    return _pooled(band - band.min(), sq_dev, count - 1.0)


def _pooled(group: np.ndarray, sq_dev: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """Each bin's variance pooled over its group (a non-negative integer per bin), or over all
    bins where the group has fewer than 3 degrees of freedom."""
    dof_group = np.bincount(group, weights=dof)
    pooled = np.bincount(group, weights=sq_dev) / np.maximum(dof_group, 1.0)
    overall = sq_dev.sum() / max(dof.sum(), 1.0)
    return np.where(dof_group[group] >= 3, pooled[group], overall)


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


def window_wanted(radius: float) -> float:
    """The half-width across the edge a spot of ``radius`` (px) asks for: its reach and as much
    again (at least 4 px) of level on each side."""
    return radius + max(4.0, radius)


def windows(task: EdgeTask, radius: float | None) -> tuple[float | tuple[float, float], float, bool]:
    """The profile's half-width across the edge, the length skipped at each end, and whether the
    clean room is too narrow for the spot's reach (``radius`` of the last reading; None: the first
    pass, which takes all the clean room on each side as far as the narrower one's). After the
    first pass the half-widths are two, (right, left) of the edge: each :func:`window_wanted`
    where that side's clean room allows, less where it does not."""
    clear = max(0.0, min(task.clear_left_px, task.clear_right_px) - 0.5)
    if radius is None:  # first pass: all the clean room, ends skipped by as much
        return clear, clear, False
    want = window_wanted(radius)
    truncated = clear - radius < radius + 1.5
    # Each side as wide as its own clean room allows: a marker beside one side of a board's edge
    # does not narrow the other, where the spot's halo and the level beyond it are seen whole
    # (the narrower side alone set both: a retrofocus's far-side cores in a halo, their reach
    # cut on both sides by the marker on one, read 3-9 % small).
    pos = max(2.0, min(want, task.clear_left_px - 0.5 - radius))
    neg = max(2.0, min(want, task.clear_right_px - 0.5 - radius))
    return (neg, pos), max(neg, pos) + radius + 1.0, truncated


def line_end_covariance(cov: np.ndarray, half_len: float, given_radius: bool = False) -> tuple[float, float, float]:
    """Covariance of the fitted edge line's offsets (across the edge, px) at its two ends, from
    the edge fit's covariance of the offset ``d0`` (index 0) and the turn (index 4, radians about
    the middle): (variance at the start, covariance, variance at the end). The turn moves the
    two ends in opposite directions, so their errors anti-correlate (about -0.6 for an even
    spread of pixels along the edge); corners refined from these lines inherit that
    (:func:`lensfit.measurement.edge_geometry.refine_corners`).

    ``given_radius``: the covariance given the squared radius (index 1), for an edge whose blur
    the fit does not determine (a sub-pixel reading: no curvature in ``R^2`` at 0). A symmetric
    blur does not move the edge, but there the fit's inverse curvature is huge along ``R^2`` and
    leaks into the offset through round-off: on a board 6 mm beyond the focus distance (an
    end-to-end fuzz's focus bracket), one line stated offsets of 71-184 px (1 sigma) for an error
    of thousandths of a pixel, and the calibration that read its corners through it stated the
    focal length to 0.2 px against an error of 4.5-6.9 px (tests/measurement/test_random_scenes.py)."""
    cov = np.asarray(cov, np.float64)
    if given_radius and np.isfinite(cov[1, 1]) and cov[1, 1] > 0:
        keep = [0, 4]
        cov = cov.copy()
        cov[np.ix_(keep, keep)] -= np.outer(cov[keep, 1], cov[1, keep]) / cov[1, 1]
    c00, c44, c04 = float(cov[0, 0]), half_len * half_len * float(cov[4, 4]), half_len * float(cov[0, 4])
    return c00 + c44 - 2.0 * c04, c00 - c44, c00 + c44 + 2.0 * c04
