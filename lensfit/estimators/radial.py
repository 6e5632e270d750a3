"""The spot's radial profile, read where two concentric disks cannot hold it.

A real lens's spot near focus, wide open, can be a bright ring with a faint halo beyond it
(undercorrected spherical aberration, the near side of focus of a fast Petzval): a third of its
second moment lies in a halo a few percent as bright as the ring. Two disks hold a core in a halo
or a rim, not both; fitted to such an edge they read the ring and miss the halo, 5-13 % small
(exact edges of an f/1.4 Petzval's real-ray spots, ``tests/estimators/test_radial_profile.py``).

Here the spot is any radial profile, piecewise constant over ``ANNULI`` equal-width rings out
to the window's reach: the edge profile is then linear in the rings' shares of the light (each
ring's pixel-integrated edge-spread function is a difference of two disks', in closed form,
``lensfit.measurement.psf``), solved by weighted linear least squares with the edge line and its turn held
where the two-disk fit put them. The second moment is the ratio of two linear functions of the
shares, ``c^2 = sum_k w_k 4 (r_{k-1}^2 + r_k^2) / sum_k w_k``, its variance from the solve's
covariance through that ratio's gradient.
The shares are not held non-negative: a constrained solve turns the noise in the outer rings
into light that is always positive, and read uniform disks 0.2-0.8 % large; unconstrained, the
reading is unbiased and only noisier.

It is noisier (on exact uniform disks in noise, 1-3 times the two-disk reading's scatter), so it
is taken only where the data reject two disks (its weighted residual sum of squares below the
two-disk fit's by more than the extra parameters explain, at ``REJECT_Z`` standard deviations of
the chi-square) and where the two readings differ by more than the rings' own 1 sigma: where
they do not, the two-disk reading's bias is below what the rings can show, and it is the less
noisy of the two. A spot two disks hold keeps their reading, unchanged. Where the outermost ring holds light,
the halo reaches the window's edge and may go on beyond it (a ChArUco board's markers leave a
window of the clean room less the spot's radius): no reading, flag ``window_truncated``, as for
any spot wider than its window.
"""

from __future__ import annotations

import math

import numpy as np

from lensfit.estimators.edge_model import squared_radius
from lensfit.measurement.psf import pixel_edge_profiles_np

#: Rings of the radial profile, out to the window's reach.
ANNULI = 8
#: The two-disk fit is rejected where the rings lower the chi-square by more than the extra
#: parameters' mean plus this many of its standard deviations (a chi-square of ANNULI - 4
#: degrees of freedom under the two-disk hypothesis).
REJECT_Z = 5.0
#: The rings reach this share of the window's smaller side.
REACH_SHARE = 0.95
#: The spot reaches the window's edge where its outermost ring holds more than this share of
#: the light, at ``REACH_Z`` standard errors: the halo may go on beyond, and the reading is
#: refused as a window too narrow for the spot (flag ``window_truncated``).
REACH_MIN_SHARE = 0.01
REACH_Z = 3.0


def _two_disk_diameter(theta) -> float:
    """The two-disk fit's second-moment diameter, 2 R sqrt(1 - a (1 - t^2))."""
    R = math.sqrt(float(squared_radius(float(theta[1]))) + 1e-12)
    t = 1.0 / (1.0 + math.exp(-float(np.clip(theta[6], -50.0, 50.0))))
    return 2.0 * R * math.sqrt(max(1.0 - float(theta[5]) * (1.0 - t * t), 0.0))


def radial_reading(profile: tuple, theta: np.ndarray, rms: float) -> tuple[float, float, bool] | None:
    """The second-moment diameter (px) of the edge's spot read as a radial profile, its 1 sigma,
    and whether the spot reaches the window's edge (its outermost ring holds light beyond
    ``REACH_Z`` standard errors: a halo the window may cut, the reading then a lower bound),
    where the data reject the two-disk fit ``theta`` (``lensfit.estimators.edge_model``: d0,
    rho, lo, hi, turn, a, logit t; ``rms``: its RMS residual in standard errors over the bins less
    its 7 parameters, as ``lensfit.estimators.edge_fit`` reports it) of the same ``profile`` (d, s,
    values, standard errors, pixel boxes); None where two disks hold the spot, or where the rings
    give no reading."""
    d, s_along, v, se, boxes = profile
    d, s_along, v, se = (np.asarray(q, np.float64) for q in (d, s_along, v, se))
    x = d - float(theta[0]) - float(theta[4]) * s_along
    w = 1.0 / se
    reach = REACH_SHARE * min(float(x.max()), float(-x.min()))
    if not (reach > 0.5 and len(x) > 3 * (ANNULI + 1)):
        return None
    r = np.linspace(0.0, reach, ANNULI + 1)
    P = pixel_edge_profiles_np(x, r, boxes)
    rings = (r[1:] ** 2 * P[:, 1:] - r[:-1] ** 2 * P[:, :-1]) / (r[1:] ** 2 - r[:-1] ** 2)
    A = np.column_stack([np.ones_like(x), rings]) * w[:, None]
    coef, *_ = np.linalg.lstsq(A, v * w, rcond=None)
    rss = float(np.sum((A @ coef - v * w) ** 2))
    extra = ANNULI + 1 - 5  # the rings' parameters beyond the two disks' R, lo, hi, a, t
    two_disk_rss = rms * rms * max(len(x) - 7, 1)
    if not two_disk_rss - rss > extra + REJECT_Z * math.sqrt(2.0 * extra):
        return None
    shares = coef[1:]
    total = float(shares.sum())
    m = 4.0 * (r[:-1] ** 2 + r[1:] ** 2)
    c2 = float(shares @ m) / total if total != 0.0 else math.nan
    if not (math.isfinite(c2) and c2 > 0.0):
        return None
    dof = max(len(x) - A.shape[1], 1)
    cov = np.linalg.pinv(A.T @ A) * max(rss / dof, 1.0)
    g = np.concatenate([[0.0], (m - c2) / total])
    var_c2 = float(g @ cov @ g)
    c = math.sqrt(c2)
    sigma = math.sqrt(max(var_c2, 0.0)) / (2.0 * c)
    if not abs(c - _two_disk_diameter(theta)) > sigma:
        return None  # the two disks' reading is as good as the rings can tell, and less noisy
    outer = shares[-1] / total, math.sqrt(max(float(cov[-1, -1]), 0.0)) / abs(total)
    reaches = outer[0] > REACH_MIN_SHARE and outer[0] > REACH_Z * outer[1]
    return c, sigma, reaches
