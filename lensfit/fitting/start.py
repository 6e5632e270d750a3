"""A closed-form start: the V's vertex by a grid search with linear least squares per vertex."""

from __future__ import annotations


import numpy as np



def vertex_search(w: np.ndarray, c: np.ndarray, sig: np.ndarray, wt: np.ndarray, fit_floor: bool,
                   floor_px: float) -> tuple[float, float, float]:
    """Closed-form start for one setting: (vertex 1/mm, slope px*mm, floor px)."""
    grid, chi2, k, b = vertex_profile(w, c, sig, wt, fit_floor, floor_px)
    best = int(np.argmin(chi2))
    return float(grid[best]), float(k[best]), float(b[best])


def vertex_profile(w: np.ndarray, c: np.ndarray, sig: np.ndarray, wt: np.ndarray, fit_floor: bool,
                    floor_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chi-square of the best V for each candidate vertex: (vertices 1/mm, chi2, slope, floor).

    For each candidate vertex x the model ``c^2 = k^2 (x - w)^2 + b^2`` is linear in
    ``(k^2, b^2)``: weighted linear least squares (weights ``1/(2 c sigma)^2``, the variance of
    ``c^2``), then the vertex with the least chi-square in ``c``. Candidates span the samples'
    inverse distances and as much again on each side, plus infinity (x = 0).
    """
    lo, hi = float(w.min()), float(w.max())
    span = max(hi - lo, 0.05 * hi)
    # The samples' own inverse distances join the grid (as quantiles: memory stays
    # O(1000 x n) for stacks of thousands of edges).
    grid = np.unique(np.concatenate([np.linspace(max(lo - span, -0.2 * hi), hi + span, 801), [0.0],
                                     np.quantile(w, np.linspace(0.0, 1.0, min(len(w), 200)))]))
    cc = np.maximum(c, 0.05)
    a2 = (grid[:, None] - w[None, :]) ** 2  # (G, n)
    wv = wt / (2 * cc * sig) ** 2
    y = c**2 - (0.0 if fit_floor else floor_px**2)
    if fit_floor:
        # Normal equations of [a2, 1] per candidate.
        s11 = a2**2 @ wv
        s12 = a2 @ wv
        s22 = wv.sum()
        t1 = a2 @ (wv * y)
        t2 = (wv * y).sum()
        det = s11 * s22 - s12**2
        k2 = np.where(det > 0, (t1 * s22 - s12 * t2) / np.where(det > 0, det, 1), 0.0)
        b2 = np.where(det > 0, (s11 * t2 - s12 * t1) / np.where(det > 0, det, 1), 0.0)
        neg = b2 < 0  # floor cannot be negative: refit the slope alone
        k2 = np.where(neg, t1 / np.maximum(s11, 1e-300), k2)
        b2 = np.where(neg, 0.0, b2)
    else:
        k2 = (a2 @ (wv * y)) / np.maximum(a2**2 @ wv, 1e-300)
        b2 = np.full_like(k2, floor_px**2)
    k2 = np.maximum(k2, 0.0)
    pred = np.sqrt(k2[:, None] * a2 + b2[:, None])
    chi2 = ((pred - c[None, :]) ** 2 * (wt / sig**2)[None, :]).sum(axis=1)
    return grid, chi2, np.sqrt(k2), np.sqrt(b2)


def one_side(w: np.ndarray, x: float) -> str | None:
    """"nearer" or "farther" when all inverse distances ``w`` lie on one side of the vertex ``x``
    (same units), else None."""
    if np.all(w > x):
        return "nearer"
    if np.all(w < x):
        return "farther"
    return None


def side_hint(w: np.ndarray, x: float) -> str:
    """"; every sample is nearer/farther than the focus" when all inverse distances ``w`` lie on
    one side of the vertex ``x`` (same units), else ""."""
    side = one_side(w, x)
    return f"; every sample is {side} than the focus" if side else ""
