"""Exact area averages of target textures over an axis-aligned grid of cells (sub-pixels).

For a fronto-parallel target the image is a pure scale of the target plane, so a sub-pixel is
an axis-aligned square on the target. Boards (checkerboard, ChArUco raster), uniform patches
and the object's own outline are piecewise constant on an axis-aligned grid: their average
over each square is ``O_y @ V @ O_x.T`` with sparse overlap matrices, exact to rounding. The
slanted-edge square uses the closed-form coverage of a square by a half-plane (exact except
within one sub-pixel of the square's four corners, where the product of two coverages is
used). Other textures (Siemens star, image files) return None: callers point-sample them.
"""

from __future__ import annotations

import math

import numpy as np


def overlap_matrix(edges_lo: np.ndarray, width: float, cell_edges: np.ndarray) -> "scipy.sparse.csr_matrix":
    """Fraction of each interval ``[lo, lo + width]`` covered by each cell ``[e_c, e_{c+1}]``."""
    lo = np.asarray(edges_lo, np.float64)
    hi = lo + width
    e = np.asarray(cell_edges, np.float64)
    nc = e.size - 1
    first = np.searchsorted(e, lo, side="right") - 1
    last = np.searchsorted(e, hi, side="left") - 1
    span = int(np.max(last - first, initial=0)) + 1
    rows, cols, vals = [], [], []
    q = np.arange(lo.size)
    for k in range(span):
        c = first + k
        ok = (c >= 0) & (c < nc) & (c <= last)
        cc = np.clip(c, 0, nc - 1)
        ov = np.minimum(hi, e[cc + 1]) - np.maximum(lo, e[cc])
        ok &= ov > 0
        rows.append(q[ok])
        cols.append(cc[ok])
        vals.append(ov[ok] / width)
    import scipy.sparse  # here: 75 ms at import, which a ray-traced render never needs

    return scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(lo.size, nc))


def _with_margin(pattern_edges: np.ndarray, half: float) -> tuple[np.ndarray, int]:
    """Pattern cell edges extended by margin cells out to +-half; returns edges and the pad before."""
    pre = [-half] if pattern_edges[0] > -half + 1e-12 else []
    post = [half] if pattern_edges[-1] < half - 1e-12 else []
    return np.concatenate([pre, pattern_edges, post]), len(pre)


def grid_description(static: tuple, raster: np.ndarray):
    """(x_edges, y_edges, values) of an axis-aligned piecewise-constant texture, or None."""
    kind = static[0]
    if kind == "uniform":
        _, w, h, value = static
        return np.array([-w / 2, w / 2]), np.array([-h / 2, h / 2]), np.array([[value]])
    if kind == "checkerboard":
        _, w, h, (nx, ny), sq, dark, light = static
        cells = (np.add.outer(np.arange(ny), np.arange(nx)) % 2 == 0)
        pattern = np.where(cells, dark, light)
        xe = (np.arange(nx + 1) - nx / 2) * sq
        ye = (np.arange(ny + 1) - ny / 2) * sq
        margin = light
    elif kind == "raster-nearest":
        _, w, h, pw, ph, margin = static
        pattern = np.asarray(raster, np.float64)
        rows, cols = pattern.shape
        xe = np.linspace(-pw / 2, pw / 2, cols + 1)
        ye = np.linspace(-ph / 2, ph / 2, rows + 1)
    else:
        return None
    xe, px = _with_margin(xe, w / 2)
    ye, py = _with_margin(ye, h / 2)
    values = np.full((ye.size - 1, xe.size - 1), margin, np.float64)
    values[py:py + pattern.shape[0], px:px + pattern.shape[1]] = pattern
    return xe, ye, values


def _halfplane_coverage(t, a, b):
    """Area of the unit square (centred at 0) where ``n . p <= t``, for a unit normal with
    ``|n_x| = a >= |n_y| = b``: linear in the middle, quadratic over the corner strips."""
    t = np.clip(t, -(a + b) / 2, (a + b) / 2)
    if b < 1e-9:
        return np.clip(t + 0.5, 0.0, 1.0)
    low = (t + (a + b) / 2) ** 2 / (2 * a * b)
    high = 1.0 - ((a + b) / 2 - t) ** 2 / (2 * a * b)
    mid = 0.5 + t / a
    return np.where(t <= -(a - b) / 2, low, np.where(t >= (a - b) / 2, high, mid))


def slanted_square_coverage(static: tuple, x_lo: np.ndarray, y_lo: np.ndarray, side: float) -> np.ndarray:
    """Fraction of each square sub-pixel (side ``side`` mm, lower corners x_lo, y_lo) inside the
    dark rotated square of a slanted-edge target."""
    _, w, h, angle, edge, dark, light = static
    ang = math.radians(angle)
    xc = (x_lo + side / 2)[None, :]
    yc = (y_lo + side / 2)[:, None]
    cover = np.ones((y_lo.size, x_lo.size))
    # The dark square is the intersection of four half-planes n_k . p <= edge/2.
    for k in range(4):
        phi = ang + k * math.pi / 2
        nx, ny = math.cos(phi), math.sin(phi)
        a, b = max(abs(nx), abs(ny)), min(abs(nx), abs(ny))
        t = (edge / 2 - (nx * xc + ny * yc)) / side  # signed distance of the centre inside, in sub-pixels
        cover = cover * _halfplane_coverage(t, a, b)
    return cover


def area_average(static: tuple, raster: np.ndarray, x_lo: np.ndarray, y_lo: np.ndarray, side: float):
    """Exact averages over square cells of (texture x coverage, coverage), or None if unsupported.

    Parameters
    ----------
    x_lo, y_lo : lower cell edges in target mm (increasing), ``side`` the cell size in mm.

    Returns
    -------
    (colour, alpha) float32 arrays of shape (y_lo.size, x_lo.size): ``colour`` is the mean of
    texture x inside-indicator, ``alpha`` the covered fraction.
    """
    w, h = static[1], static[2]
    if static[0] == "slanted-edge":
        ox = overlap_matrix(x_lo, side, np.array([-w / 2, w / 2]))
        oy = overlap_matrix(y_lo, side, np.array([-h / 2, h / 2]))
        alpha = np.outer(np.asarray(oy.sum(axis=1)).ravel(), np.asarray(ox.sum(axis=1)).ravel())
        _, _, _, _, _, dark, light = static
        dark_cover = slanted_square_coverage(static, x_lo, y_lo, side)
        colour = light * alpha - (light - dark) * np.minimum(dark_cover, alpha)
        return colour.astype(np.float32), alpha.astype(np.float32)
    grid = grid_description(static, raster)
    if grid is None:
        return None
    xe, ye, values = grid
    ox = overlap_matrix(x_lo, side, xe)
    oy = overlap_matrix(y_lo, side, ye)
    # The large products formed in float32 (each output a sum of a few overlaps; rounding ~1e-7,
    # far below a 16-bit step): float64 ones and their float32 copies took 0.5 s of a 13 MP grid.
    colour = oy.astype(np.float32) @ np.ascontiguousarray((ox @ values.T).T, np.float32)
    alpha = np.outer(np.asarray(oy.sum(axis=1), np.float32).ravel(), np.asarray(ox.sum(axis=1), np.float32).ravel())
    return np.asarray(colour, np.float32), alpha
