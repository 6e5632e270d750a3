"""The spot read across a ChArUco marker's light stripe, where the clean room cuts its tails.

Beside a light square's edge a ChArUco board leaves a light stripe as wide as the gap to the
marker (``(square - marker) / 2``), then the marker's black border, one of its cells wide. The
edge estimators' window ends a spot's radius short of the marker, so that its blur stays out:
on a fast lens's aberrated spots (a halo, or off the axis a comatic tail on one side) that is
short of the light the spot spreads, and the symmetric profiles fitted there read small or not
at all. Exact edges of an f/1.4 Petzval's real-ray spots 240 px off the axis, on the near side of
focus, with a marker 14.6 px beyond the edge: 0.73-0.86 of their second moment (0.85-0.99 with
clean room); on the axis (``tests/estimators/test_marker_stripe.py``) more than 5 % small or refused.

Here the window runs on across the stripe and into the border (to the border's far side less the
spot's reach ``support``), and the image there is modelled as what it is: the stripe
``1[0 < x < g]`` (or its mirror) blurred by the spot's line-spread function, which is any
function over ``BINS`` equal bins across ``[-support, support]``: linear in the bins' shares of
the light (a bin's edge-spread function is a ramp, integrated over the pixel's footprint in closed
form; the stripe's is the difference of two at ``g`` apart), solved by weighted linear least
squares with the edge line and its turn held where the two-disk fit put them, unconstrained. The
spot's variance across the edge is the histogram's about its own mean (within a bin uniform:
``w^2 / 12``), ``c = 4 sigma``; its 1 sigma from the solve's covariance through that ratio's
gradient. On the Petzval's exact edges beside a marker: 0.94-1.00 of the second moment off the
axis near focus, 0.99-1.00 far from it; on the axis within 4 % (the test).

It is noisier than the symmetric readings (more parameters over more of the image) and it needs
the stripe's width from the board's geometry, so it replaces them only where the two differ by
more than ``DIFFER_Z`` of their combined noise (on a uniform disk they agree, and the symmetric
reading stays): flag ``marker_stripe``.
"""

from __future__ import annotations

import math

import numpy as np

from lensfit.measurement.psf import over_pixel_boxes

#: Bins of the line-spread histogram across ``[-support, support]``: at most BINS, no finer than
#: the profile's sampling, and at least MIN_BINS (else no reading).
BINS = 16
MIN_BINS = 6
#: The spot's reach (px) the histogram spans, as a multiple of the first pass's disk radius,
#: within [SUPPORT_MIN_PX, the border's width less BORDER_MARGIN_PX].
SUPPORT_RADII = 2.0
#: ... and at least this many (else the border is too narrow for the spot: no reading).
MIN_SUPPORT_RADII = 1.5
SUPPORT_MIN_PX = 4.0
BORDER_MARGIN_PX = 2.0
#: The stripe's reading replaces the symmetric one where they differ by more than this many of
#: their combined 1 sigma (noise), and its own 1 sigma is under MAX_SIGMA_SHARE of it.
DIFFER_Z = 3.0
MAX_SIGMA_SHARE = 0.1
#: ... and by more than this share of the symmetric reading: on exact uniform disks the two
#: readings part by up to about 1 % (the histogram's bins, the pixel footprint), which is no
#: shape the symmetric profile missed.
MIN_DIFFERENCE_SHARE = 0.05
#: Above this reduced chi-square the model does not hold the edge: no reading.
MAX_REDUCED_CHI2 = 3.0


def bin_edge_profiles(x: np.ndarray, edges: np.ndarray, boxes) -> np.ndarray:
    """``(len(x), len(edges) - 1)``: the edge-spread function at ``x`` of a unit of light spread
    evenly over each bin ``[edges[k], edges[k + 1]]``, integrated over the pixel footprint
    ``boxes`` (``lensfit.estimators.profile.footprint``): a ramp from each bin edge, whose second
    antiderivative is ``max(t, 0)^3 / 6``, differenced over the bin."""
    def cube(t):
        return np.maximum(t, 0.0) ** 3 / 6.0
    Q = over_pixel_boxes(cube, np.asarray(x, np.float64)[:, None] - np.asarray(edges, np.float64)[None, :], boxes)
    return (Q[:, :-1] - Q[:, 1:]) / np.diff(edges)[None, :]


def marker_side(task) -> int:
    """+1 where the marker's border lies on the edge's left (positive normal distance), -1 on its
    right, 0 where neither side has one (``EdgeTask.border_*_px``)."""
    if task.border_left_px > 0.0 and task.border_right_px <= 0.0:
        return 1
    if task.border_right_px > 0.0 and task.border_left_px <= 0.0:
        return -1
    return 0


def stripe_window(task, radius: float) -> tuple[tuple[float, float], float, float] | None:
    """The window ((right, left) half-widths, px) across the edge for a spot of first-pass disk
    radius ``radius``, the length skipped at each end, and the histogram's reach; None where the
    task has no marker on one side, or its border is too narrow to see beyond the stripe."""
    side = marker_side(task)
    if side == 0:
        return None
    gap, band = (task.clear_left_px, task.border_left_px) if side > 0 else (task.clear_right_px, task.border_right_px)
    other = task.clear_right_px if side > 0 else task.clear_left_px
    support = min(max(SUPPORT_RADII * radius, SUPPORT_MIN_PX), band - BORDER_MARGIN_PX)
    if not support >= max(SUPPORT_MIN_PX, MIN_SUPPORT_RADII * radius):
        return None  # the border is too narrow for the spot's reach
    marker = gap + band - support  # short of the border's far side by the spot's reach
    open_side = min(other - support - 0.5, 2.0 * support + 4.0)
    if not open_side >= support + 2.0:
        return None
    half = (open_side, marker) if side > 0 else (marker, open_side)
    return half, max(half) + support + 1.0, support


def stripe_reading(profile: tuple, theta: np.ndarray, task, support: float) -> tuple[float, float] | None:
    """The second-moment diameter (px) of the edge's spot read across the marker's stripe, and
    its 1 sigma; None where it gives none. ``profile``: (d, s, values, standard errors, pixel
    boxes) over :func:`stripe_window`'s window; ``theta``: the two-disk fit of the edge
    (``lensfit.estimators.edge_model``), whose line (offset, turn) is held."""
    side = marker_side(task)
    gap = task.clear_left_px if side > 0 else task.clear_right_px
    d, s_along, v, se, boxes = profile
    d, s_along, v, se = (np.asarray(q, np.float64) for q in (d, s_along, v, se))
    x = d - float(theta[0]) - float(theta[4]) * s_along
    if len(x) <= 3 * (BINS + 1):
        return None
    # Bins no finer than the profile's sampling across the spot (its 90th percentile step): an
    # edge along a pixel axis samples it once per pixel, and finer bins there are not determined.
    inside = np.sort(x[np.abs(x) < support])
    if inside.size < 3:
        return None
    sampling = float(np.percentile(np.diff(inside), 90.0))
    bins = min(BINS, int(2.0 * support / sampling)) if sampling > 0 else BINS
    if bins < MIN_BINS:
        return None
    edges = np.linspace(-support, support, bins + 1)
    # the stripe 1[0 < side * x < gap]: the edge's step less the marker's, along the side
    columns = bin_edge_profiles(x, edges, boxes) - bin_edge_profiles(x - side * gap, edges, boxes)
    A = np.column_stack([np.ones_like(x), columns]) / se[:, None]
    coef, *_ = np.linalg.lstsq(A, v / se, rcond=None)
    rss = float(np.sum((A @ coef - v / se) ** 2))
    dof = max(len(x) - A.shape[1], 1)
    if not rss / dof <= MAX_REDUCED_CHI2:
        return None  # the model does not hold the image (the stripe is not where the board puts it)
    shares = coef[1:]
    total = float(shares.sum())
    if total == 0.0:
        return None
    mid, width = 0.5 * (edges[:-1] + edges[1:]), np.diff(edges)
    second = mid * mid + width * width / 12.0
    m1, m2 = float(shares @ mid) / total, float(shares @ second) / total
    var = m2 - m1 * m1
    if not (math.isfinite(var) and var > 0.0):
        return None
    cov = np.linalg.pinv(A.T @ A) * max(rss / dof, 1.0)
    g = np.concatenate([[0.0], (second - m2 - 2.0 * m1 * (mid - m1)) / total])
    c = 4.0 * math.sqrt(var)
    sigma = 16.0 * math.sqrt(max(float(g @ cov @ g), 0.0)) / (2.0 * c)
    return (c, sigma) if math.isfinite(sigma) else None
