"""Pixels whose value the ray tracer need not sample: every ray of the pixel meets one region of
constant reflectance (or no object at all), so the Monte-Carlo mean is that constant exactly.

A pixel's rays start in its square (the box filter) and pass through the aperture disk. For a
block of B x B pixels take the 4 corners of the block and the 8 vertices of a regular octagon
circumscribed about the aperture (radius A/2 / cos(pi/8)): the ray from any lens point through
any point of the block hits a plane inside the convex hull of the 32 hits of those corner rays.
(For a fixed lens point the map from sensor point to hit point is a central projection, and so
is the map from lens point to hit point for a fixed sensor point; both keep convex hulls where
no ray of the bundle is parallel to the plane or meets it behind the lens, which is checked: the
ray parameter's numerator and denominator are affine in the lens and sensor points and keep one
sign over the bundle when they keep it at the 32 vertex rays.) The hull's bounding box, grown by
a tolerance far above the float32 rounding of the tracer (2e-5 of the coordinates' size), is then
tested against each object's rectangle and texture:

- missed: the box lies outside the rectangle, so no ray of the block hits the object;
- covered with one value: the box lies inside the rectangle and the texture is constant over
  it (a uniform patch; one square of a checkerboard or its margin; a box of equal texels of a
  ChArUco raster, read from summed tables of the raster's neighbour differences, or its margin).

A block is constant where every object is missed (the background) or exactly one object covers
it with one value and every other is missed; its pixels take that value. Blocks are 4 px
squares whose corners are shared with their neighbours (one grid of corner rays per lens
vertex and object). Textures of other kinds (slanted edges, Siemens stars, image files) are
never declared constant where a block touches them. Under lens distortion a block's corners are
those of a box holding its pixels' samples in the undistorted image (their own per block, not
shared). Not used (every pixel traced) with a compound lens or a front stop (optical vignetting).

The values are exact where the tracer's are Monte-Carlo means of identical samples (equal to
float32 rounding of that mean; tested on tilted, macro, infinity-focus, occluding and
multi-object shots and bladed and squeezed apertures against full sampling, and against the
thin-lens geometry on a fronto-parallel board). On the demo stack 65-95 % of a shot's pixels
are constant, decided in 10-30 ms a shot.
"""

from __future__ import annotations

import math

import numpy as np

#: Block size (px): a block's hull grows with it (fewer constant pixels), the cost of deciding
#: falls with its square. On the demo stack's shots 4 px blocks leave 5-35 % of the pixels to
#: trace, decided in 10-30 ms a shot (2 px: 3-30 %, 35-90 ms; 8 px: 11-42 %, 4-23 ms).
BLOCK = 4
#: Below this many samples per pixel deciding costs more than the samples it saves (measured on
#: the demo stack by `synth bench`).
MIN_SPP = 4
_NV = 8
_ANGLES = (np.arange(_NV) + 0.5) * (2 * math.pi / _NV)
#: The lens vertices: a regular octagon circumscribed about the unit circle.
_LENS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], 1) / math.cos(math.pi / _NV)
_TOLERANCE = 2e-5  # of |depth| + |u| + |v| (mm); the tracer's float32 errors are about 1e-6 of them


def shape_reach(aperture: tuple) -> float | None:
    """How far the aperture's shape reaches from its centre, in units of the circle of diameter
    A (``synth.effects.aperture.sample``'s unit disk): the radius of a disk holding it; None for
    an unknown shape."""
    kind = aperture[0]
    if kind in ("circle", "polygon"):
        return 1.0
    if kind == "anamorphic":
        return max(1.0, 1.0 / float(aperture[1]))
    return None


def constant_pixels(structure: tuple, rasters, planes: np.ndarray, cam: np.ndarray, width: int, height: int,
                    background: float, aperture: tuple = ("circle",), warp: np.ndarray | None = None) -> np.ndarray:
    """(height, width) float32: each pixel's exact value where every ray of it meets one constant
    region (or nothing), NaN where it must be traced. ``structure``, ``rasters``, ``planes`` and
    ``cam`` are the tracer's (``synth.raytrace.scene_arrays``, ``camera_array``: a thin lens);
    ``warp`` its lens distortion (``synth.effects.distortion.pixel_warp``), if any."""
    reach = shape_reach(aperture)
    if reach is None:
        return np.full((height, width), np.nan, np.float32)
    cam = np.asarray(cam, np.float64)
    lens = 0.5 * float(cam[4]) * reach * _LENS
    planes = np.asarray(planes, np.float64)
    nby, nbx = -(-height // BLOCK), -(-width // BLOCK)
    if warp is None:
        # The blocks' corners (pixel coordinates of the pixels' outer edges), shared by neighbours.
        qx = (np.arange(nbx + 1) * BLOCK - 0.5)[None, :]
        qy = (np.arange(nby + 1) * BLOCK - 0.5)[:, None]
    else:
        qx, qy = _warped_corners(np.asarray(warp, np.float64), nby, nbx)
    mixed = np.zeros((nby, nbx), bool)
    touched = np.zeros((nby, nbx), np.int32)
    value = np.full((nby, nbx), float(background))
    for k, static in enumerate(structure):
        ahead, u0, u1, v0, v1 = _hull(qx, qy, planes[k], cam, lens, per_block=warp is not None)
        half_w, half_h = 0.5 * static[1], 0.5 * static[2]
        missed = (u1 < -half_w) | (u0 > half_w) | (v1 < -half_h) | (v0 > half_h)
        inside = (u0 > -half_w) & (u1 < half_w) & (v0 > -half_h) & (v1 < half_h)
        constant = np.full((nby, nbx), np.nan)
        todo = ahead & inside & ~missed
        if todo.any():
            constant[todo] = _texture_constant(static, np.asarray(rasters[k]), u0[todo], u1[todo], v0[todo], v1[todo])
        covered = todo & np.isfinite(constant)
        mixed |= ~(ahead & (missed | covered))
        touched += ~missed
        value = np.where(covered, constant, value)
    blocks = np.where(~mixed & (touched <= 1), value, np.nan).astype(np.float32)
    return np.ascontiguousarray(np.repeat(np.repeat(blocks, BLOCK, axis=0), BLOCK, axis=1)[:height, :width])


def _warped_corners(warp: np.ndarray, nby: int, nbx: int) -> tuple[np.ndarray, np.ndarray]:
    """Per block, the corners (nby, nbx, 4) of a box in pinhole pixel coordinates that holds every
    sample of its pixels under the distortion: a pixel's samples lie in the parallelogram of its
    warp (``synth.raytrace._render_pixels``: centre plus the derivatives times offsets of at
    most half a pixel)."""
    u, v = warp[..., 0], warp[..., 1]
    eu = 0.5 * (np.abs(warp[..., 2]) + np.abs(warp[..., 3]))
    ev = 0.5 * (np.abs(warp[..., 4]) + np.abs(warp[..., 5]))
    pad = ((0, nby * BLOCK - u.shape[0]), (0, nbx * BLOCK - u.shape[1]))

    def per_block(a, reduce):  # the edge pixels stand in for the padding (a block's box only grows)
        return reduce(np.pad(a, pad, mode="edge").reshape(nby, BLOCK, nbx, BLOCK), axis=(1, 3))
    u0, u1 = per_block(u - eu, np.min), per_block(u + eu, np.max)
    v0, v1 = per_block(v - ev, np.min), per_block(v + ev, np.max)
    return np.stack([u0, u1, u0, u1], axis=-1), np.stack([v0, v0, v1, v1], axis=-1)


def _hull(qx: np.ndarray, qy: np.ndarray, plane: np.ndarray, cam: np.ndarray, lens: np.ndarray, per_block: bool):
    """Per block: whether every corner ray meets the plane ahead of the lens, and the bounding box
    (u0, u1, v0, v1) of their hits in the target frame, grown by the tolerance. The corners are a
    grid shared by neighbouring blocks (qx a row, qy a column), or ``per_block`` each block's own
    four (the last axis)."""
    cx, cy, scale, inverse_focus = cam[0], cam[1], cam[2], cam[3]
    c, ex, ey, nrm = plane[0:3], plane[3:6], plane[6:9], plane[9:12]
    shape = np.broadcast_shapes(qx.shape, qy.shape)
    lo_u, lo_v = np.full(shape, np.inf), np.full(shape, np.inf)
    hi_u, hi_v = np.full(shape, -np.inf), np.full(shape, -np.inf)
    size = np.zeros(shape)
    ahead = np.ones(shape, bool)
    for lx, ly in lens:
        dx = (qx - cx) * scale - lx * inverse_focus  # the tracer's thin_lens_ray
        dy = (qy - cy) * scale - ly * inverse_focus
        denom = dx * nrm[0] + dy * nrm[1] + nrm[2]
        num = (c[0] - lx) * nrm[0] + (c[1] - ly) * nrm[1] + c[2] * nrm[2]
        ahead &= (np.abs(denom) > 1e-9) & (abs(num) > 1e-9) & (np.sign(denom) == np.sign(num))
        z = num / np.where(denom == 0, 1.0, denom)
        hx, hy, hz = lx + z * dx - c[0], ly + z * dy - c[1], z - c[2]
        u = hx * ex[0] + hy * ex[1] + hz * ex[2]
        v = hx * ey[0] + hy * ey[1] + hz * ey[2]
        np.minimum(lo_u, u, out=lo_u)
        np.maximum(hi_u, u, out=hi_u)
        np.minimum(lo_v, v, out=lo_v)
        np.maximum(hi_v, v, out=hi_v)
        np.maximum(size, np.abs(z) + np.abs(u) + np.abs(v), out=size)

    def corners(a, reduce):  # over each block's four corners
        if per_block:
            return reduce.reduce(a, axis=-1)
        return reduce(reduce(a[:-1, :-1], a[:-1, 1:]), reduce(a[1:, :-1], a[1:, 1:]))
    tol = _TOLERANCE * corners(size, np.maximum) + 1e-6
    return (corners(ahead, np.logical_and), corners(lo_u, np.minimum) - tol, corners(hi_u, np.maximum) + tol,
            corners(lo_v, np.minimum) - tol, corners(hi_v, np.maximum) + tol)


def _texture_constant(static: tuple, raster: np.ndarray, u0, u1, v0, v1) -> np.ndarray:
    """The texture's value where it is constant over the box [u0, u1] x [v0, v1] (target mm),
    NaN elsewhere (``synth.textures.evaluate``'s conventions)."""
    kind = static[0]
    if kind == "uniform":
        return np.full(u0.shape, float(static[3]))
    if kind == "checkerboard":
        _, _, _, (nx, ny), sq, dark, light = static
        i0, i1 = np.floor((u0 + 0.5 * nx * sq) / sq), np.floor((u1 + 0.5 * nx * sq) / sq)
        j0, j1 = np.floor((v0 + 0.5 * ny * sq) / sq), np.floor((v1 + 0.5 * ny * sq) / sq)
        off = (i1 < 0) | (i0 >= nx) | (j1 < 0) | (j0 >= ny)
        one = (i0 == i1) & (j0 == j1) & (i0 >= 0) & (i0 < nx) & (j0 >= 0) & (j0 < ny)
        cell = np.where(np.mod(i0 + j0, 2.0) == 0.0, dark, light)
        return np.where(off, light, np.where(one, cell, np.nan))
    if kind == "raster-nearest":
        _, _, _, pw, ph, margin = static
        rows, cols = raster.shape
        c0, c1 = (u0 + 0.5 * pw) * (cols / pw), (u1 + 0.5 * pw) * (cols / pw)
        r0, r1 = (v0 + 0.5 * ph) * (rows / ph), (v1 + 0.5 * ph) * (rows / ph)
        off = (c1 < 0) | (c0 >= cols) | (r1 < 0) | (r0 >= rows)
        on = (c0 >= 0) & (c1 < cols) & (r0 >= 0) & (r1 < rows)
        ci0, ci1 = (np.clip(np.floor(a), 0, cols - 1).astype(np.int64) for a in (c0, c1))
        ri0, ri1 = (np.clip(np.floor(a), 0, rows - 1).astype(np.int64) for a in (r0, r1))
        across, down = _difference_tables(raster)
        equal = (_box(across, ri0, ri1, ci0 + 1, ci1) == 0) & (_box(down, ri0 + 1, ri1, ci0, ci1) == 0)
        return np.where(off, float(margin), np.where(on & equal, raster[ri0, ci0], np.nan))
    return np.full(u0.shape, np.nan)


def _difference_tables(raster: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Summed-area tables of where a texel differs from its left and its upper neighbour."""
    across = np.zeros(raster.shape, np.int64)
    across[:, 1:] = raster[:, 1:] != raster[:, :-1]
    down = np.zeros(raster.shape, np.int64)
    down[1:, :] = raster[1:, :] != raster[:-1, :]

    def summed(a):
        s = np.zeros((a.shape[0] + 1, a.shape[1] + 1), np.int64)
        s[1:, 1:] = a.cumsum(0).cumsum(1)
        return s
    return summed(across), summed(down)


def _box(table: np.ndarray, r0, r1, c0, c1) -> np.ndarray:
    """Sums over rows r0..r1 and columns c0..c1 (inclusive; 0 where a range is empty)."""
    return table[r1 + 1, c1 + 1] - table[r0, c1 + 1] - table[r1 + 1, c0] + table[r0, c0]
