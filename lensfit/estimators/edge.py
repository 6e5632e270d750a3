"""``edge``: the slanted-edge method, reporting the blur's second-moment diameter.

PSF model
    The uniform disk of radius R of a thin lens (the circle of confusion), or where the spot is
    visibly no uniform disk, two concentric uniform disks: a share ``a`` of the light in a disk
    of radius ``t R`` (0 < t < 1) and ``1 - a`` in one of radius R. ``a > 0`` is a bright core in
    a halo, ``a < 0`` (down to ``-t^2 / (1 - t^2)``, where the centre's intensity reaches 0) a
    bright rim: the two faces of spherical aberration on either side of a real lens's focus.
    Where the data reject two disks too (a bright ring in a faint halo), any radial profile of
    eight rings (``lensfit.estimators.radial``, flag ``radial_profile``).
    Both integrated over square pixels with 100 % fill factor in closed form
    (``lensfit.measurement.psf.pixel_edge_profile``). No Gaussian stand-in: a Gaussian fitted to a disk is
    biased.
What "blur diameter" means
    The second-moment diameter ``c = 4 sigma``, sigma the spot's standard deviation across the
    edge: for a uniform disk exactly its diameter, for any other spot the diameter of the
    uniform disk with the same variance (``c = 2 R sqrt(1 - a (1 - t^2))`` for two disks).
    Variances of convolved blurs add, so this is the quantity the fit's model
    ``sqrt((A S |1/D - 1/d| / p)^2 + b^2)`` describes; far from focus it grows as the real
    entrance pupil's cone, and its V's vertex is the lens's best (least-RMS) focus. A
    uniform-disk fit to an aberrated spot misses it by up to 10 %, a one-parameter rim/core
    profile ``1 + beta (2 rho^2 - 1)`` by up to 8 % on a bright core in a wide halo;
    two disks follow both within 0.5 % noise-free (``edge-disk`` keeps the uniform disk).
Method
    Pixels near a straight target edge are projected onto the edge normal, which super-samples
    the edge profile (ISO 12233 / MTF Mapper practice). The model
    ``lo + (hi - lo) * ESF_pixel(d - d0; R, a, t)`` is fitted in float64 by Levenberg-Marquardt
    (``lensfit.fitting.lm``; parameters: edge offset d0, R^2 (a smooth max(., 0)), the two levels, the
    line's turn), started from a grid search over the radius with the levels solved linearly;
    first as a uniform disk (a = 0), then, wherever the spot's shape can be read (a disk reading
    of ``SHAPE_MIN_PX`` or more), again as two disks (a and t free, priors a ~ 0 +- 1 and
    logit t ~ 0 +- 2), solved with the second moment ``m R^2`` as a parameter in place of ``R^2``
    (``edge_model.moment_residuals``), started from the best of a grid of cores, rims and the
    uniform disk itself that keep the disk's second moment (two disks have more than one local
    minimum; with the disk among the starts the fit never ends worse than it); flag ``shaped_spot``, the disk's
    reading kept beside it (``disk_diameter_px``), its sigma the fit's own in quadrature with a
    model error of ``SHAPE_MODEL_SHARE`` of the two readings' difference (on a uniform disk they
    agree to the noise; read this way a pure disk's scatter grows by under a fifth at 2-3 px and
    not at all from 4 px, and its bias stays within 0.1 %). Only where the blur is the same
    along the edge: at one depth (within 1 %), or, from ``SHAPE_ACROSS_MIN_PX``, with the disk
    diameters of its two halves within ``SHAPE_MAX_STRIP_SPREAD`` of each other; elsewhere the
    profile mixes spots of several sizes, which the fit's model describes as the power mean of a
    uniform-disk reading. (Shaped only on edges at one depth and beyond 1.5 standard errors, the
    tilted boards' core-and-halo spots of a retrofocus lens at f/5.6 read 7-18 % small, N 3 %
    high with them; shaped only where the disk misfit beyond the noise, a telephoto's at f/11
    read 0.7 % small on the far side of focus and 0.25 % large on the near side, its focus
    distance 0.28 % long.) The window across the edge
    widens with the blur (radius + max(4 px, radius)) up to the clean room the target leaves on
    each side, and the ends of the segment are skipped by the window plus the blur, so that
    neither truncates the PSF nor lets neighbouring squares in. Beside a ChArUco marker, where
    that window ends short of a fast lens's halo or comatic tail, the spot is also read across
    the marker's light stripe into its black border (``lensfit.estimators.stripe``, flag
    ``marker_stripe``), and that reading replaces the symmetric one where they part by more than
    its noise and 5 %. The profile has 1/8 px bins, or
    128 across a wider window; a bin's value is the profile averaged over its pixels' positions,
    so the model's pixel footprint is widened by their spread (``profile.footprint``: left out,
    it read exact edges 0.9 % / c^2 wide). Every edge of a stack is fitted in one batched solve per pass
    (``measure_images``; ``jax.vmap`` over chunks of 16 edges, 4 for two disks and the Airy
    pattern, of 64 or 256 bins, each chunk solved as soon as it is full while the next profiles
    are gathered): two compiled shapes per kind of fit, whatever the stack
    (``lensfit.estimators.edge_fit``). The profile model, the residuals and the start grids are
    in ``lensfit.estimators.edge_model``.
Diffraction
    Where the caller gives the Airy scale ``a = lambda N_w / p`` (``airy_px``; the pipeline of
    ``lensfit fit --diffraction``), the model profile is the one above convolved with the Airy
    line-spread function and the pixel (``lensfit.measurement.diffraction.edge_kernel``: a piecewise-linear
    kernel of 97 knots per edge, exact against the disk), plus a ramp across the window (weak
    prior) for the Airy tails of the target's neighbouring edges; the reading is then the
    defocus blur alone. The spot's shape is not read there (the Airy core and rings are the
    shape; a lens stopped down that far has little aberration left), and the first pass, which
    only sizes the window, reads a uniform disk, whose radius bounds the start of the second.
Uncertainty
    1 sigma from the Gauss-Newton covariance ``(J^T W J)^-1``, each profile bin weighted by its
    standard error (the noise variance where it lies, never its own spread, which read noisy
    blurs low: ``lensfit.estimators.profile``; at least a model-error floor of 3e-4 of the edge
    contrast per pixel; the two-disk fit keeps per-band spreads), inflated by the reduced
    chi-square when the model misfits, combined in quadrature with 0.3 % of c + 0.02 px
    (perspective across a segment), so that noise-free images do not claim impossible
    precision. Edges within 2 degrees of a pixel axis are barely super-sampled and flagged
    ``axis_aligned``; their sigma is larger, as it should be.
Valid range
    c from about 0.5 px (below that the pixel footprint dominates: a sub-pixel reading is
    stated with 0.2 px, flag ``sub_pixel_blur``) up to the clean room across the edge; beyond
    it (a window narrower than the spot's radius + 1.5 px on either side) there is no value,
    flag ``window_truncated``: on a retrofocus lens at f/5.6, whose halo reaches past such
    windows, those readings came out 19 % low (median) at -6.7 of their sigmas, and N 4-6 %
    high with them. A profile that does not determine c gives no value (flag
    ``blur_undetermined``): 1 sigma above 3 c (the covariance is inverted with a ridge, so an
    undetermined direction shows as a huge variance, not as none), or for a sub-pixel reading
    a blur of 1 px fitting less than 4 in chi-square worse (the rest held: a lenient test).
Cost
    About 1.4-1.9 ms per edge warm on 2 cores (12 images of 0.96-1.5 MP; 2.1 ms on 3 images), all
    passes and profiles, every edge's shape read (lensfit bench-stages); with diffraction
    modelled the second pass costs 6-9 times the disk's.
Reference
    ISO 12233:2017; F. van den Bergh, MTF Mapper (slanted-edge projection); the disk ESF, e.g.
    W. J. Smith, *Modern Optical Engineering*.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from lensfit.measurement.diffraction import MAX_AIRY_PX
from lensfit.estimators.base import BlurEstimate, EdgeTask, Flag, with_model_floor
from lensfit.estimators.edge_fit import FitQueue, fit_profiles
from lensfit.estimators.edge_model import MIN_VARIANCE_SHARE, squared_radius, squared_radius_slope
from lensfit.estimators.profile import line_end_covariance, select as _select, window_wanted, windows
from lensfit.estimators.radial import radial_reading
from lensfit.estimators.stripe import DIFFER_Z as STRIPE_DIFFER_Z, MAX_SIGMA_SHARE as STRIPE_MAX_SIGMA_SHARE
from lensfit.estimators.stripe import MIN_DIFFERENCE_SHARE as STRIPE_MIN_SHARE
from lensfit.estimators.stripe import stripe_reading, stripe_window
from lensfit.runtime.parallel import in_threads

SUB_PIXEL_PX = 0.5
SUB_PIXEL_SIGMA_PX = 0.2
#: A reading (c >= SUB_PIXEL_PX) whose 1 sigma exceeds this multiple of c is no reading (flag
#: ``blur_undetermined``, no value); a sub-pixel one is none unless a blur of ``edge_fit.PROBE_C_PX`` fits
#: worse by PROBE_DCHI2 in chi-square.
UNDETERMINED_SIGMA = 3.0
PROBE_DCHI2 = 4.0
AXIS_ALIGNED_DEG = 2.0  # edges closer than this to a pixel axis are barely super-sampled
#: Smallest blur diameter (disk reading) whose spot shape is read (from it, on every edge where
#: the blur is even along it): below it the pixel footprint dominates the profile and two disks
#: are not told from one (a 2 px core-and-halo spot in 1 % noise reads 12 % low, docs/src/explanation/estimators.md).
SHAPE_MIN_PX = 2.0
#: Largest relative change of depth along an edge that counts as one depth: on such an edge the
#: spot's shape is read at once.
SHAPE_MAX_DEPTH_SPAN = 0.01
#: On an edge across depth the shape is read where the uniform-disk diameters of its two halves
#: differ by at most this fraction of their mean (the blur changes by about twice that from end
#: to end, and the two-disk reading of that mixture of spots, the RMS of their diameters, differs
#: from the power mean the fit's model takes by under 0.2 %; see ``_even_along``).
SHAPE_MAX_STRIP_SPREAD = 0.1
#: ... and where its uniform-disk reading is at least this wide. Smaller spots of a thin lens
#: stopped down (synth's camera-raw scene: f/11, Airy scale 1-1.5 px) look like a core in a halo
#: too, and the two-disk reading counts the Airy tails into the second moment (3 px spots read
#: 35-45 % large, 6-7 px ones 11-15 %, against 15-25 % and 6-8 % through the uniform disk): shaping
#: every even edge took that stack's N 4.6 % low where it is fitted without the diffraction model
#: (from 6 px: 0.2 %). On the retrofocus at f/5.6 (Airy scale 0.5 px) the tilted boards' 8-12 px
#: core-in-a-halo spots are what needs it: far N +0.7 % of the real-ray f-number (none: +3.1 %).
SHAPE_ACROSS_MIN_PX = 6.0
#: Model error (1 sigma) of a shaped reading, as a share of its difference from the uniform
#: disk's: two disks follow real-ray spots within 0.15-0.3 of what the disk misses (a core in a
#: halo: 2.5 % where the disk reads 8 % small; 0.1 % where it reads 0.7 % small); on a uniform
#: disk the two agree to the noise. Below: how many sigmas of a make a shape significant.
SHAPE_MODEL_SHARE = 0.3
SHAPE_SIGNIFICANT_Z = 2.0


def _at_one_depth(task: EdgeTask) -> bool:
    """Whether the edge lies at one depth (within ``SHAPE_MAX_DEPTH_SPAN``), or its depths are not
    known. Along an edge across depth the spot changes size, and the profile is a mixture of
    spots: the fit describes that by the power mean of a uniform-disk reading
    (``lensfit.fitting.constants.BLUR_POWER_MEAN``), so the shape is read there only where the blur
    is still the same along the edge (:func:`_even_along`)."""
    depths = task.context.get("end_depths_mm")
    if not depths:
        return True
    z0, z1 = depths
    return abs(z1 - z0) <= SHAPE_MAX_DEPTH_SPAN * 0.5 * abs(z0 + z1)


def _even_along(profiles: list[tuple]) -> list[bool]:
    """Per edge profile (d, s, values, standard errors, normal; binned in ``STRIPS`` strips along
    the edge), whether its blur is the same along the edge to ``SHAPE_MAX_STRIP_SPREAD``: a
    uniform disk fitted to each half of the strips gives diameters c1, c2, and the edge is even
    where ``|c1 - c2| <= SHAPE_MAX_STRIP_SPREAD (c1 + c2) / 2``. A spot's shape biases both
    halves' disk readings alike, so their ratio measures the change of blur along the edge.
    Where a half has too few bins, not even."""
    halves, owner = [], []
    for k, (d, s, v, se, n) in enumerate(profiles):
        mid = 0.5 * (float(s.min()) + float(s.max()))
        parts = [s < mid, s >= mid]
        if min(int(p.sum()) for p in parts) < 8:
            continue
        for p in parts:
            halves.append((d[p], s[p], v[p], se[p], n))
            owner.append(k)
    out = [False] * len(profiles)
    fits = fit_profiles(halves, False)
    for i in range(0, len(fits), 2):
        (t1, _, _, ok1, _), (t2, _, _, ok2, _) = fits[i], fits[i + 1]
        c1, c2 = (2.0 * math.sqrt(squared_radius(float(t[1]))) for t in (t1, t2))
        out[owner[i]] = bool(ok1 and ok2 and abs(c1 - c2) <= SHAPE_MAX_STRIP_SPREAD * 0.5 * (c1 + c2))
    return out


def _radius_terms(theta, cov) -> tuple[float, float, float, float]:
    """Of a fit: R^2, d R^2 / d rho, the variance of R^2, and 1 sigma of R from it,
    ``sqrt(R^2 + sigma_rho) - R`` (= sigma_rho / 2R when R is well determined, sqrt(sigma_rho) as
    R -> 0)."""
    rho = float(squared_radius(float(theta[1])))
    slope = squared_radius_slope(float(theta[1]))
    var_rho = slope * slope * float(cov[1, 1])
    return rho, slope, var_rho, math.sqrt(rho + math.sqrt(max(var_rho, 0.0))) - math.sqrt(rho)


def _load(source: Any) -> np.ndarray:
    return np.asarray(source() if callable(source) else source, np.float64)


def measure(image: np.ndarray, tasks: list[EdgeTask], second_moment: bool = True,
            airy_px: float | None = None) -> list[BlurEstimate]:
    """Blur diameter at each edge of one image (see the module docstring): the second-moment
    diameter, or with ``second_moment=False`` the diameter of the best-fitting uniform disk.
    ``airy_px``: the Airy pattern's scale ``lambda N_w / p`` where diffraction is modelled
    (``lensfit.measurement.diffraction``); the reading is then the defocus blur alone."""
    return measure_images([(image, tasks)], second_moment, airy_px=None if airy_px is None else [airy_px])[0]


def measure_images(items: list[tuple[Any, list[EdgeTask]]], second_moment: bool = True,
                   progress: Callable[[int], None] | None = None,
                   airy_px: list[float] | None = None, keep_profiles: dict[str, Any] | None = None,
                   profiles: dict[str, Any] | None = None) -> list[list[BlurEstimate]]:
    """:func:`measure` on the edges of many images in one batched solve per pass.

    ``items``: (image, tasks) pairs; an image may be given as a zero-argument callable that
    returns it, called once per pass (twice in all), so that a stack need not be held in memory.
    ``progress(k)`` is called as item k's edges are ready for the last solve. ``airy_px``: per
    item, the Airy scale in px where diffraction is modelled (None: nowhere). Returns the
    estimates per item, in order.

    ``keep_profiles``: a dict this call fills with the last pass's profiles and what the first
    pass found (window, start, edge position); ``profiles``: such a dict from a call on the same
    images and edges, whose profiles are then solved again (with ``airy_px``) instead of being
    gathered anew. The first pass and the profiles do not depend on the Airy scale (the first
    pass reads a uniform disk), so the estimates are those of a call without ``profiles``; a
    dict from other edges is ignored. Such a call keeps its solutions with the Airy pattern in
    the dict, and the next one starts its fits from them instead of from a grid over the first
    pass's radius (the same minima: readings within 1e-7, but for sub-pixel blurs on a flat
    cost, within 0.0003 px; the fits a third faster). ``lensfit.measurement.pipeline``'s diffraction rounds
    re-read the same edges at a new Airy scale each (0.15 s of a 10-shot bracket's 0.6 s a
    round, warm)."""
    items = list(items)
    if airy_px is not None:
        if len(airy_px) != len(items) or not all(math.isfinite(a) and 0.0 <= a <= MAX_AIRY_PX for a in airy_px):
            raise ValueError(f"airy_px: one scale per image, each between 0 and {MAX_AIRY_PX} px")
    owner = [k for k, (_, ts) in enumerate(items) for _ in ts]
    tasks = [t for _, ts in items for t in ts]
    # per edge: its reading, the last pass's radius, its line, the first pass's (offset, radius),
    # the profile with the two-disk fit's weights; flags, pixels, whether the second pass's window
    # is narrower than the spot asks for, the profile across a marker's stripe (beside one)
    results, radius, lines, expected, banded = ([None] * len(tasks) for _ in range(5))
    flags, npixels, cramped, stripes = [[] for _ in tasks], [0] * len(tasks), [False] * len(tasks), {}
    key = [(k, tuple(float(x) for x in t.start_px), tuple(float(x) for x in t.end_px), float(t.clear_left_px),
            float(t.clear_right_px)) for k, t in zip(owner, tasks)]
    reuse = profiles if profiles is not None and profiles.get("key") == key else None
    for attempt in range(2):
        if reuse is not None and attempt == 0:
            continue  # the first pass's findings are in the kept profiles
        batch, index, images = [], [], {}  # profiles solved this pass, their edges, the image in hand
        # The first pass only sizes the window: a uniform disk (which takes the Airy pattern for
        # blur, so the window comes out wider, never narrower) at a tenth of the cost or less;
        # its radius bounds the start of the fit with the pattern. Each full chunk is solved
        # while the next profiles are gathered.
        with_airy = airy_px is not None and attempt == 1
        # An earlier call's solutions with the Airy pattern (at the last round's scale, a nearby
        # one) start these: a third less time than the grid from the first pass's radius.
        earlier = reuse.get("airy_theta") if with_airy and reuse is not None else None
        if reuse is not None:
            results, radius, flags, npixels, lines, expected, banded, batch, index, cramped = (
                list(v) for v in reuse["state"])
            if earlier is not None and not all(i in earlier for i in index):
                earlier = None
        queue = FitQueue(False, with_airy, warm=earlier is not None)

        def enqueue(i, profile):  # with the Airy pattern: from an earlier call's solution or the first pass's radius
            if not with_airy:
                return queue.add(profile)
            start = earlier[i] if earlier is not None else np.array([0.0, radius[i] ** 2, 0.0, 1.0, 0.0])
            queue.add(profile, start, float(airy_px[owner[i]]))
        if reuse is not None:
            for i, profile in zip(index, batch):
                enqueue(i, profile)
        else:
            skip = [results[i] is not None and attempt == 1 and radius[i] is None for i in range(len(tasks))]
            # The next image is read in a background thread while this one's edges are gathered
            # (decoding releases the GIL): a stack too large to hold is read again with its reading
            # hidden behind the gathering, two images in memory at a time.
            loader = in_threads(_load, [items[k][0] for k in dict.fromkeys(o for o, s in zip(owner, skip) if not s)],
                                jobs=2)
            try:
                for i, task in enumerate(tasks):
                    if skip[i]:
                        continue
                    if owner[i] not in images:
                        images.clear()  # one image in memory at a time (and the next one being read)
                        images[owner[i]] = next(loader)
                    got = _profile_of(images[owner[i]], task, radius[i] if attempt else None,
                                      expected[i] if attempt else None)
                    if got is None:
                        results[i] = BlurEstimate(None, None, (Flag.TOO_FEW_PIXELS,), 0)
                        radius[i] = None
                        continue
                    profile, banded[i], lines[i], f, npixels[i], narrowed = got
                    if attempt:
                        flags[i], cramped[i] = f, narrowed
                        stripes[i] = _stripe_profile(images[owner[i]], task, radius[i]) if second_moment else None
                    batch.append(profile)
                    index.append(i)
                    enqueue(i, profile)
            finally:
                loader.close()
        if attempt == 1 and keep_profiles is not None:
            keep_profiles.update(key=key, state=tuple(list(v) for v in (
                results, radius, flags, npixels, lines, expected, banded, batch, index, cramped)))
        images.clear()
        if progress and attempt == 1:
            for k in range(len(items)):
                progress(k)
        airy = [float(airy_px[owner[i]]) for i in index] if with_airy else None
        fits = queue.results()
        if with_airy and reuse is not None:  # for the next round's start
            reuse["airy_theta"] = {i: np.asarray(fits[j][0][:5], np.float64) for j, i in enumerate(index) if fits[j][3]}
        shaped, disk, radial, halo_cut, across = set(), {}, {}, set(), {}
        if second_moment and attempt == 1 and airy is None:
            fits, shaped, disk, radial, halo_cut, across = _read_shapes(
                fits, [tasks[i] for i in index], batch, [banded[i] for i in index], [flags[i] for i in index],
                [cramped[i] for i in index], [stripes.get(i) for i in index])
        for j, (i, fitted) in enumerate(zip(index, fits)):
            results[i], reach, where = _reading(fitted, flags[i], npixels[i], lines[i], batch[j], j in shaped,
                                                disk.get(j), radial.get(j), j in halo_cut, across.get(j))
            radius[i] = reach  # None where the fit failed
            if reach is not None:
                expected[i] = where
    out: list[list[BlurEstimate]] = [[] for _ in items]
    for k, r in zip(owner, results):
        out[k].append(r if r is not None else BlurEstimate(None, None, (Flag.NOT_MEASURED,)))
    return out


def _profile_of(image: np.ndarray, task: EdgeTask, radius: float | None, expected: tuple[float, float] | None):
    """An edge's profile for a pass (``radius`` of the last pass's reading; None: the first
    pass): (profile, profile with the two-disk fit's weights, (line, normal), flags, pixels,
    whether the clean room narrowed the window below what the spot asks for); None where too few
    pixels lie in the window."""
    half, margin, truncated = windows(task, radius)
    sel = _select(image, task, half, margin, expected)
    if sel is None or len(sel[0]) < 8:
        return None
    d, s_along, v, se, n, L, short, pixels, line, se_banded, boxes = sel
    flags: list[Flag] = []
    if radius is not None:
        flags = ([Flag.WINDOW_TRUNCATED] if truncated else []) + ([Flag.SHORT_EDGE] if short else [])
        angle = math.degrees(math.atan2(abs(n[1]), abs(n[0])))
        if min(angle, 90.0 - angle) < AXIS_ALIGNED_DEG:
            flags.append(Flag.AXIS_ALIGNED)
    narrowed = radius is not None and min(half) < window_wanted(radius) - 1e-9
    return (d, s_along, v, se, boxes), (d, s_along, v, se_banded, boxes), (line, n), flags, pixels, narrowed


def _read_shapes(fits: list, tasks: list[EdgeTask], batch: list, banded: list, flags: list[list[Flag]],
                 cramped: list[bool], stripes: list) -> tuple[list, set[int], dict, dict, set[int], dict]:
    """The spot's shape read wherever it can be (see the module docstring), the uniform disk's
    reading kept beside it (their difference sizes the shape's model error): the fits with the
    shaped ones in place, which were shaped, each one's disk (diameter, RMS, sigma), the radial
    profile's (diameter, sigma) where two disks could not hold the spot, the spots whose halo
    goes on past a window the clean room narrowed, and beside a marker the reading across its
    stripe (diameter, sigma, or None). Per fit: its task, profile, profile with the two-disk
    weights, flags, whether the clean room narrowed its window, and its profile across a marker's
    stripe (``_stripe_profile``, or None)."""
    fits = list(fits)
    diameter = [2.0 * math.sqrt(squared_radius(float(theta[1]))) for theta, *_ in fits]
    readable = [j for j, (_, _, _, ok, _) in enumerate(fits) if ok and diameter[j] >= SHAPE_MIN_PX]
    across = [j for j in readable if not _at_one_depth(tasks[j])]
    wide = [j for j in across if diameter[j] >= SHAPE_ACROSS_MIN_PX]
    uneven = set(across) - {j for j, ok in zip(wide, _even_along([batch[j] for j in wide])) if ok}
    shaped = [j for j in readable if j not in uneven]
    disk: dict[int, tuple[float, float, float]] = {}
    radial: dict[int, tuple[float, float]] = {}
    halo_cut: set[int] = set()
    for j, refit in zip(shaped, fit_profiles([banded[j] for j in shaped], True, [fits[j][0] for j in shaped])):
        disk[j] = (diameter[j], fits[j][2], 2.0 * _radius_terms(*fits[j][:2])[3])
        fits[j] = refit
        if refit[3] and Flag.WINDOW_TRUNCATED not in flags[j]:  # where two disks cannot hold it
            got = radial_reading(banded[j], np.asarray(refit[0], np.float64), refit[2])
            if got is not None and got[2] and cramped[j]:  # a halo the clean room cut
                halo_cut.add(j)
            elif got is not None:
                radial[j] = got[:2]
    striped = {j: _across_stripe(stripes[j], fits[j], tasks[j]) for j in shaped}
    return fits, set(shaped), disk, radial, halo_cut, striped


def _stripe_profile(image: np.ndarray, task: EdgeTask, radius: float) -> tuple | None:
    """The profile across the marker's stripe beside ``task`` (``lensfit.estimators.stripe``) for
    a spot of first-pass radius ``radius``, with the histogram's reach; None where there is none."""
    window = None if radius is None else stripe_window(task, radius)
    if window is None:
        return None
    half, margin, support = window
    sel = _select(image, task, half, margin, None)
    if sel is None or len(sel[0]) < 8:
        return None
    d, s_along, v, se, *_, boxes = sel
    return (d, s_along, v, se, boxes), support


def _across_stripe(stripe: tuple | None, fitted: tuple, task: EdgeTask) -> tuple[float, float] | None:
    """The stripe's reading of an edge (diameter, 1 sigma) from its profile and the edge's
    two-disk fit ``fitted``; None where there is none."""
    if stripe is None or not fitted[3]:
        return None
    profile, support = stripe
    return stripe_reading(profile, np.asarray(fitted[0], np.float64), task, support)


def _reading(fitted: tuple, flags: list[Flag], npixels: int, line: tuple, profile: tuple, shaped: bool,
             disk: tuple[float, float, float] | None, radial: tuple[float, float] | None,
             halo_cut: bool, stripe: tuple[float, float] | None = None
             ) -> tuple[BlurEstimate, float | None, tuple[float, float] | None]:
    """One edge's reading from its fit ``(theta, cov, rms, ok, probe)``: the estimate, the outer
    disk's radius (the spot's reach, for the next pass's window) and where the next pass's
    noise model puts the edge (offset, radius); None for both where the fit failed. ``disk``,
    ``radial``: :func:`_read_shapes`' for this edge."""
    theta, cov, rms, ok, probe = fitted
    rho, slope, var_rho, sigma_r = _radius_terms(theta, cov)
    r = math.sqrt(rho)
    a = float(theta[5]) if shaped else 0.0
    t = 1.0 / (1.0 + math.exp(-float(np.clip(theta[6], -50.0, 50.0))))
    m = 1.0 - a * (1.0 - t * t)  # variance of two disks over that of the outer one
    if not (ok and np.isfinite(r) and np.isfinite(var_rho) and np.isfinite(a) and m > MIN_VARIANCE_SHARE):
        return BlurEstimate(None, None, tuple(flags) + (Flag.FIT_FAILED,), npixels), None, None
    reach = (r, (float(theta[0]), r))
    # The second-moment diameter c = 2 R sqrt(1 - a (1 - t^2)): 16 x the spot's variance across
    # the edge; the uniform disk's diameter where a = 0.
    k = math.sqrt(m)
    c = 2.0 * r * k
    f = list(flags) + ([Flag.SHAPED_SPOT] if shaped else []) + ([Flag.WINDOW_TRUNCATED] if halo_cut else [])
    # 1 sigma of c from that of R (_radius_terms); the shape's share by the gradient of c in
    # (a, logit t), with its covariance with R^2.
    var_c = (2.0 * k * sigma_r) ** 2
    if shaped:
        g = np.array([-r * (1.0 - t * t) / k, 2.0 * r * a * t * t * (1.0 - t) / k])
        C = np.asarray(cov[5:7, 5:7], np.float64)
        var_c += float(g @ C @ g) + 2.0 * (k / max(r, 1e-6)) * slope * float(g @ np.asarray(cov[1, 5:7]))
    sigma_c = math.sqrt(max(var_c, (2.0 * k * sigma_r) ** 2 * 0.25))
    if radial is not None:  # two disks could not hold it: the radial profile's reading
        c, noise = radial
        f.append(Flag.RADIAL_PROFILE)
        sigma_c = math.hypot(noise, SHAPE_MODEL_SHARE * abs(c - disk[0]))
    elif shaped:
        # Chi-square inflation measures the profile family's misfit, which the model error states
        # instead (a share of how far the spot reads from a uniform disk). Where a is within
        # SHAPE_SIGNIFICANT_Z sigmas of 0 the noise is the disk fit's: at a = 0 the two disks'
        # covariance overstates it (a pure disk's scatter: +0-15 %; sigma: +30 %).
        noise = (disk[2] if abs(a) < SHAPE_SIGNIFICANT_Z * math.sqrt(max(float(cov[5, 5]), 0.0))
                 else sigma_c / max(rms, 1.0))
        sigma_c = math.hypot(noise, SHAPE_MODEL_SHARE * abs(c - disk[0]))
    if stripe is not None and shaped and stripe[1] < STRIPE_MAX_SIGMA_SHARE * stripe[0] and (
            abs(stripe[0] - c) > max(STRIPE_DIFFER_Z * math.hypot(stripe[1], noise), STRIPE_MIN_SHARE * c)):
        # the marker's stripe shows more of the spot than the symmetric profile's window, which
        # the marker may have cut short of the spot's reach: its window holds the reach
        c, noise = stripe
        f = [flag for flag in f if flag != Flag.WINDOW_TRUNCATED] + [Flag.MARKER_STRIPE]
        sigma_c = math.hypot(noise, SHAPE_MODEL_SHARE * abs(c - disk[0]))
    sigma = with_model_floor(sigma_c, c)
    if c < SUB_PIXEL_PX:
        # Below about half a pixel the pixel footprint dominates the profile and the fit's
        # curvature says nothing useful (none at R = 0): the reading is "sharp", stated with
        # 0.2 px, if the profile rules out a 1 px blur (by chi-square PROBE_DCHI2); else it says
        # nothing (an edge along a pixel axis in noise, whose few pixel phases trade the radius
        # against the edge's position).
        undetermined = not probe >= PROBE_DCHI2
        sigma = SUB_PIXEL_SIGMA_PX
        f.append(Flag.SUB_PIXEL_BLUR)
    else:
        undetermined = not sigma <= UNDETERMINED_SIGMA * c
    if undetermined:
        return BlurEstimate(None, None, tuple(f) + (Flag.BLUR_UNDETERMINED,), npixels), *reach
    contrast = abs(float(theta[3] - theta[2]))
    if contrast < 10 * max(rms, 1e-12) * float(np.median(profile[3])):
        f.append(Flag.LOW_CONTRAST)
    (q0, q1), n = line
    d0, turn = float(theta[0]), float(theta[4])
    half_len = 0.5 * float(np.linalg.norm(q1 - q0))
    line_px = (tuple(float(x) for x in q0 + (d0 - turn * half_len) * n),
               tuple(float(x) for x in q1 + (d0 + turn * half_len) * n))
    # A window that cannot hold the spot's reach gives no value (the line is kept for the
    # corners): such readings came out 2-40 % low, their sigmas not saying so.
    cut = Flag.WINDOW_TRUNCATED in f
    d_c, d_rms, d_sigma = disk if shaped and not cut else (None, rms, None)
    return BlurEstimate(None if cut else c, None if cut else sigma, tuple(f), npixels, d_rms, line_px, d_c,
                        None if d_c is None else with_model_floor(d_sigma, d_c),
                        line_end_covariance(np.asarray(cov, np.float64), half_len, Flag.SUB_PIXEL_BLUR in f),
                        tuple(float(x) for x in math.copysign(1.0, float(theta[3] - theta[2])) * n)), *reach
