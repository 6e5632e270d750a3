"""``edge``: the slanted-edge method, reporting the blur's second-moment diameter.

PSF model
    The uniform disk of radius R of a thin lens (the circle of confusion), or where the spot is
    visibly no uniform disk, two concentric uniform disks: a share ``a`` of the light in a disk
    of radius ``t R`` (0 < t < 1) and ``1 - a`` in one of radius R. ``a > 0`` is a bright core in
    a halo, ``a < 0`` (down to ``-t^2 / (1 - t^2)``, where the centre's intensity reaches 0) a
    bright rim: the two faces of spherical aberration on either side of a real lens's focus.
    Both integrated over square pixels with 100 % fill factor in closed form
    (``lensfit.psf.pixel_edge_profile``). No Gaussian stand-in: a Gaussian fitted to a disk is
    biased.
What "blur diameter" means
    The second-moment diameter ``c = 4 sigma``, sigma the spot's standard deviation across the
    edge: for a uniform disk exactly its diameter, for any other spot the diameter of the
    uniform disk with the same variance (``c = 2 R sqrt(1 - a (1 - t^2))`` for two disks).
    Variances of convolved blurs add, so this is the quantity the fit's model
    ``sqrt((A S |1/D - 1/d| / p)^2 + b^2)`` describes; far from focus it grows as the real
    entrance pupil's cone, and its V's vertex is the lens's best (least-RMS) focus. A
    uniform-disk fit to an aberrated spot misses it by up to 10 %, a one-parameter rim/core
    profile ``1 + beta (2 rho^2 - 1)`` (tried) by up to 8 % on a bright core in a wide halo;
    two disks follow both within 0.5 % noise-free (``edge-disk`` keeps the uniform disk).
Method
    Pixels near a straight target edge are projected onto the edge normal, which super-samples
    the edge profile (ISO 12233 / MTF Mapper practice). The model
    ``lo + (hi - lo) * ESF_pixel(d - d0; R, a, t)`` is fitted in float64 with optimistix
    Levenberg-Marquardt (parameters: edge offset d0, radius R, the two levels, the line's turn),
    started from a grid search over the radius with the levels solved linearly; first as a
    uniform disk (a = 0), and where that misfits beyond the noise (RMS residual above
    ``SHAPE_RMS`` standard errors) again as two disks (a and t free, priors a ~ 0 +- 1 and
    logit t ~ 0 +- 2), from two starts (a core, a rim), the better kept; flag ``shaped_spot``,
    its sigma a 3 % model error in quadrature with the fit's own. Only on edges at one depth
    (within 1 %): along an edge across depth the profile mixes spots of several sizes, which
    the fit's model describes as the power mean of a uniform-disk reading. The window across the edge
    widens with the blur (radius + max(4 px, radius)) up to the clean room the target leaves on
    each side, and the ends of the segment are skipped by the window plus the blur, so that
    neither truncates the PSF nor lets neighbouring squares in. Edges are fitted in batches
    (``jax.vmap``), one compilation per batch shape.
Uncertainty
    1 sigma from the Gauss-Newton covariance ``(J^T W J)^-1`` with each profile bin weighted by
    its own standard error (from the spread of its pixels, never below a model-error floor of
    3e-4 of the edge contrast per pixel), inflated by the reduced chi-square when the model
    misfits, combined in
    quadrature with 0.3 % of c + 0.02 px (perspective across a segment), so that noise-free
    images do not claim impossible precision. Edges within 2 degrees of a pixel axis are
    barely super-sampled and flagged ``axis_aligned``; their sigma is larger, as it should be.
Valid range
    c from about 0.5 px (below that the pixel footprint dominates and c is weakly determined:
    the sigma says so) up to the clean room across the edge; beyond it the result is flagged
    ``window_truncated``.
Cost
    About 0.2-1 ms per edge after compilation (see the README's benchmark).
Reference
    ISO 12233:2017; F. van den Bergh, MTF Mapper (slanted-edge projection); the disk ESF, e.g.
    W. J. Smith, *Modern Optical Engineering*.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.estimators.base import BlurEstimate, EdgeTask, with_model_floor
from lensfit.psf import pixel_edge_profile

MIN_PIXELS = 24
RADIUS_GRID = np.geomspace(0.05, 200.0, 24)
OFFSET_GRID = np.linspace(-0.8, 0.8, 3)
BATCH = 16
QUANTISATION_VARIANCE = (1.0 / 65535.0) ** 2 / 12.0
MODEL_FLOOR_INTENSITY = 3e-4
SUB_PIXEL_PX = 0.5
SUB_PIXEL_SIGMA_PX = 0.2
AXIS_ALIGNED_DEG = 2.0  # edges closer than this to a pixel axis are barely super-sampled
#: Prior 1 sigma of the inner disk's share of the light, a (about 0), and of logit t, the inner
#: radius over the outer one (about 0: t = 1/2); weak, they hold the shape where the blur is too
#: small to show one.
SHARE_PRIOR = 1.0
RATIO_PRIOR = 2.0
#: Starts of the two-disk fit (a, logit t): a bright core in a halo, and a bright rim.
SHAPE_STARTS = ((0.3, -0.5), (-0.5, 1.5))
#: RMS residual (in standard errors of the profile bins) of the uniform-disk fit above which the
#: profile's shape is fitted too.
SHAPE_RMS = 1.5
#: Largest relative change of depth along an edge on which the spot's shape is read.
SHAPE_MAX_DEPTH_SPAN = 0.01
#: Model error (relative, 1 sigma) of the second moment read through the shaped profile.
SHAPE_MODEL_REL = 0.03


BIN_PX = 1.0 / 8.0  # super-sampling of the edge profile (ISO 12233 uses 1/4 px)
STRIPS = 2


def _select(image: np.ndarray, task: EdgeTask, half_width: float, end_margin: float):
    """Pixels within ``half_width`` of the edge line and at least ``end_margin`` from its ends,
    with the line re-fitted to the image and the profile binned.

    Returns (d, v, se, normal, length, shortened, pixels) or None: ``d`` the mean normal distance
    and ``v`` the mean value of the pixels in each 1/8 px bin (per strip along the edge), ``se`` the standard error of that
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
    idx = np.floor(d / BIN_PX).astype(int)
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
    floor = (MODEL_FLOOR_INTENSITY * (np.percentile(v, 95) - np.percentile(v, 5))) ** 2 + QUANTISATION_VARIANCE
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


def _model(theta, d, s, nx, ny):
    # theta = (d0, rho = R^2, lo, hi, turn, a, u): the squared radius keeps the model smooth and
    # well-conditioned as the blur vanishes (the profile depends on R only to second order
    # there); `turn` rotates the edge line (radians) about the window's middle, so that the
    # line's own uncertainty is part of the covariance; `a` is the inner disk's share of the
    # light and t = sigmoid(u) its radius over R (a = 0: the uniform disk).
    d0, rho, lo, hi, turn, a, u = (theta[i] for i in range(7))
    R = jnp.sqrt(jnp.abs(rho) + 1e-12)
    x = d - d0 - turn * s
    outer = pixel_edge_profile(x, R, nx, ny)
    inner = pixel_edge_profile(x, R * jax.nn.sigmoid(u), nx, ny)
    return lo + (hi - lo) * (outer + a * (inner - outer))


def _residuals(theta, args):
    d, s, v, w, nx, ny, shaped = args  # w = 1 / standard error of the bin mean; 0 for padding
    # shaped = 0: the uniform disk (a does not enter the model). The shape has weak priors that
    # hold it where the blur is too small to show one.
    theta = theta.at[5].multiply(shaped)
    return jnp.concatenate([w * (v - _model(theta, d, s, nx, ny)),
                            jnp.stack([theta[5] / SHARE_PRIOR, theta[6] / RATIO_PRIOR])])


def _grid_start(d, s, v, w, nx, ny):
    """Best (offset, radius) on a grid, with the two levels solved by weighted linear least squares."""
    radii, offsets = np.meshgrid(RADIUS_GRID, OFFSET_GRID)
    radii, offsets = jnp.asarray(radii.ravel()), jnp.asarray(offsets.ravel())

    def rss(radius, offset):
        p = pixel_edge_profile(d - offset, radius, nx, ny)
        A = jnp.stack([w * (1 - p), w * p], axis=1)
        coef, _, _, _ = jnp.linalg.lstsq(A, w * v)
        r = w * v - A @ coef
        return jnp.sum(r * r), coef

    costs, coefs = jax.vmap(rss)(radii, offsets)
    k = jnp.argmin(costs)
    return jnp.stack([offsets[k], radii[k] ** 2, coefs[k][0], coefs[k][1], 0.0, 0.0, 0.0])


@partial(jax.jit, static_argnames=("shaped",))
def _fit_batch(d, s, v, w, nx, ny, shaped: bool):
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
    shape = 1.0 if shaped else 0.0

    def one(d, s, v, w, nx, ny):
        args = (d, s, v, w, nx, ny, shape)
        y0 = _grid_start(d, s, v, w, nx, ny)

        def solve(start):
            sol = optx.least_squares(_residuals, solver, start, args=args, max_steps=400, throw=False)
            r = _residuals(sol.value, args)
            return sol.value, jnp.sum(r * r), sol.result == optx.RESULTS.successful

        # Two disks have more than one local minimum: start from a core and from a rim, keep the
        # better; the uniform disk has one start.
        runs = [solve(y0.at[5].set(a).at[6].set(u)) for a, u in SHAPE_STARTS] if shaped else [solve(y0)]
        best = jnp.argmin(jnp.stack([c for _, c, _ in runs]))
        theta = jnp.stack([t for t, _, _ in runs])[best]
        ok = jnp.stack([o for _, _, o in runs])[best]
        J = jax.jacfwd(_residuals)(theta, args)
        r = _residuals(theta, args)[:-2]
        n_eff = jnp.sum(w > 0)  # bins
        # Residuals are in units of each bin's own standard error; a reduced chi-square above 1
        # (model misfit) inflates the covariance, one below 1 does not shrink it.
        dof = jnp.maximum(n_eff - 5 - 2 * shape, 1)  # a and t are parameters only when shaped
        chi2 = jnp.maximum(jnp.sum(r * r) / dof, 1.0)
        JTJ = J.T @ J
        cov = chi2 * jnp.linalg.pinv(JTJ, rtol=1e-14)
        s2 = jnp.sum(r * r) / dof
        return theta, cov, jnp.sqrt(s2), ok

    return jax.vmap(one)(d, s, v, w, nx, ny)


def _bucket(n: int, minimum: int) -> int:
    return max(minimum, 1 << int(math.ceil(math.log2(max(n, 1)))))


def _fit(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], shaped: bool = True):
    """Fit a list of (d, s, values, standard errors, normal); returns theta, cov, rms, ok per item."""
    if not samples:
        return []
    npix = _bucket(max(len(s[0]) for s in samples), 128)
    nbatch = BATCH * math.ceil(len(samples) / BATCH)
    D = np.tile(np.linspace(-4.0, 4.0, npix), (nbatch, 1))  # padding rows: a harmless dummy problem
    V = np.zeros((nbatch, npix))
    S = np.zeros((nbatch, npix))
    W = np.zeros((nbatch, npix))
    NX = np.ones(nbatch)
    NY = np.zeros(nbatch)
    for i, (d, s_along, v, se, n) in enumerate(samples):
        D[i, :len(d)], S[i, :len(d)], V[i, :len(d)], W[i, :len(d)] = d, s_along, v, 1.0 / se
        NX[i], NY[i] = n
    parts = []
    with jax.enable_x64(True):
        for k in range(0, nbatch, BATCH):  # fixed batch shape: one compilation per pixel bucket
            sl = slice(k, k + BATCH)
            parts.append([np.asarray(x) for x in _fit_batch(jnp.asarray(D[sl]), jnp.asarray(S[sl]), jnp.asarray(V[sl]),
                                                            jnp.asarray(W[sl]), jnp.asarray(NX[sl]),
                                                            jnp.asarray(NY[sl]), shaped=shaped)])
    theta, cov, rms, ok = (np.concatenate([p[j] for p in parts]) for j in range(4))
    return [(theta[i], cov[i], float(rms[i]), bool(ok[i])) for i in range(len(samples))]


def _at_one_depth(task: EdgeTask) -> bool:
    """Whether the edge lies at one depth (within ``SHAPE_MAX_DEPTH_SPAN``), or its depths are not
    known. Along an edge across depth the spot changes size, and the profile is a mixture of
    spots: the fit describes that by the power mean of a uniform-disk reading
    (``lensfit.fit.constants.BLUR_POWER_MEAN``), so the shape is not read there."""
    depths = task.context.get("end_depths_mm")
    if not depths:
        return True
    z0, z1 = depths
    return abs(z1 - z0) <= SHAPE_MAX_DEPTH_SPAN * 0.5 * abs(z0 + z1)


def _windows(task: EdgeTask, radius: float | None):
    clear = max(0.0, min(task.clear_left_px, task.clear_right_px) - 0.5)
    if radius is None:  # first pass: all the clean room, ends skipped by as much
        return clear, clear, False
    want = radius + max(4.0, radius)
    room = clear - radius
    half = max(2.0, min(want, room))
    truncated = room < radius + 1.5
    return half, half + radius + 1.0, truncated


def measure(image: np.ndarray, tasks: list[EdgeTask], second_moment: bool = True) -> list[BlurEstimate]:
    """Blur diameter at each edge (see the module docstring): the second-moment diameter, or with
    ``second_moment=False`` the diameter of the best-fitting uniform disk."""
    image = np.asarray(image, np.float64)
    results: list[BlurEstimate | None] = [None] * len(tasks)
    radius: list[float | None] = [None] * len(tasks)
    flags: list[list[str]] = [[] for _ in tasks]
    npixels = [0] * len(tasks)
    lines: list = [None] * len(tasks)
    for attempt in range(2):
        batch, index = [], []
        for i, task in enumerate(tasks):
            if results[i] is not None and attempt == 1 and radius[i] is None:
                continue
            half, margin, truncated = _windows(task, radius[i] if attempt else None)
            sel = _select(image, task, half, margin)
            if sel is None or len(sel[0]) < 8:
                results[i] = BlurEstimate(None, None, ("too_few_pixels",), 0)
                radius[i] = None
                continue
            d, s_along, v, se, n, L, short, pixels, line = sel
            lines[i] = (line, n)
            if attempt == 1:
                flags[i] = (["window_truncated"] if truncated else []) + (["short_edge"] if short else [])
                angle = math.degrees(math.atan2(abs(n[1]), abs(n[0])))
                if min(angle, 90.0 - angle) < AXIS_ALIGNED_DEG:
                    flags[i].append("axis_aligned")
            batch.append((d, s_along, v, se, n))
            npixels[i] = pixels
            index.append(i)
        fits = _fit(batch, False)
        shaped: list[int] = []
        if second_moment and attempt == 1:
            # Where a uniform disk does not follow the profile (a misfit beyond the noise), the
            # shaped profile is fitted; elsewhere the disk's diameter is the second-moment one.
            shaped = [j for j, (_, _, rms, _) in enumerate(fits)
                      if rms > SHAPE_RMS and _at_one_depth(tasks[index[j]])]
            for j, refit in zip(shaped, _fit([batch[j] for j in shaped], True)):
                fits[j] = refit
        is_shaped = set(shaped)
        for j, (i, (theta, cov, rms, ok)) in enumerate(zip(index, fits)):
            rho = abs(float(theta[1]))
            r = math.sqrt(rho)
            a = float(theta[5]) if j in is_shaped else 0.0
            t = 1.0 / (1.0 + math.exp(-float(np.clip(theta[6], -50.0, 50.0))))
            m = 1.0 - a * (1.0 - t * t)  # variance of two disks over that of the outer one
            var_rho = float(cov[1, 1])
            if not (ok and np.isfinite(r) and np.isfinite(var_rho) and np.isfinite(a) and m > 0.05):
                results[i] = BlurEstimate(None, None, tuple(flags[i]) + ("fit_failed",), npixels[i])
                radius[i] = None
                continue
            radius[i] = r  # the outer disk: the spot's reach, for the window
            # The second-moment diameter c = 2 R sqrt(1 - a (1 - t^2)): 16 x the spot's variance
            # across the edge; the uniform disk's diameter where a = 0.
            k = math.sqrt(m)
            c = 2.0 * r * k
            f = list(flags[i]) + (["shaped_spot"] if j in is_shaped else [])
            # 1 sigma of R from that of R^2: sqrt(R^2 + sigma_rho) - R (= sigma_rho / 2R when R is
            # well determined, sqrt(sigma_rho) as R -> 0); the shape's share by the gradient of c
            # in (a, logit t), with its covariance with R^2.
            sigma_r = math.sqrt(rho + math.sqrt(max(var_rho, 0.0))) - r
            var_c = (2.0 * k * sigma_r) ** 2
            if j in is_shaped:
                g = np.array([-r * (1.0 - t * t) / k, 2.0 * r * a * t * t * (1.0 - t) / k])
                C = np.asarray(cov[5:7, 5:7], np.float64)
                var_c += float(g @ C @ g) + 2.0 * (k / max(r, 1e-6)) * float(g @ np.asarray(cov[1, 5:7]))
            sigma_c = math.sqrt(max(var_c, (2.0 * k * sigma_r) ** 2 * 0.25))
            if "shaped_spot" in f:
                # A spot that is no uniform disk: the fit's chi-square inflation measures how far
                # the profile family is from the spot, not how uncertain its second moment is;
                # that is stated by the family's model error instead.
                sigma_c = math.hypot(sigma_c / max(rms, 1.0), SHAPE_MODEL_REL * c)
            sigma = with_model_floor(sigma_c, c)
            if c < SUB_PIXEL_PX:
                # Below about half a pixel the pixel footprint dominates the profile and the fit's
                # curvature overstates what is known about c (seen on ray-traced edges).
                sigma = max(sigma, SUB_PIXEL_SIGMA_PX)
                f.append("sub_pixel_blur")
            contrast = abs(float(theta[3] - theta[2]))
            if contrast < 10 * max(rms, 1e-12) * float(np.median(batch[j][3])):
                f.append("low_contrast")
            (q0, q1), n = lines[i]
            d0, turn = float(theta[0]), float(theta[4])
            half_len = 0.5 * float(np.linalg.norm(q1 - q0))
            line_px = (tuple(float(x) for x in q0 + (d0 - turn * half_len) * n),
                       tuple(float(x) for x in q1 + (d0 + turn * half_len) * n))
            results[i] = BlurEstimate(c, sigma, tuple(f), npixels[i], rms, line_px)
    return [r if r is not None else BlurEstimate(None, None, ("not_measured",)) for r in results]
