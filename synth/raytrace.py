"""``raytrace``: thin-lens Monte-Carlo ray tracing of planar scenes.

For every pixel sample (the course's "ray tracing for defocus blur"):

1. a point in the pixel footprint (stratified jitter: pixel integration with a box filter);
2. a point on the aperture disk (stratified concentric-disk mapping, Shirley & Chiu 1997);
3. the ray from that lens point through the point of the plane of focus that the pixel's
   chief ray hits (``synth.geometry`` gives the formulas; focus at infinity is exact);
4. the nearest intersection with the scene's planes (so occlusion is exact);
5. the texture at the hit (point-sampled; the Monte-Carlo average over pixel and aperture
   samples is the filter), or the background when nothing is hit.

Exact for every planar scene up to Monte-Carlo noise, which falls like 1/sqrt(spp).

Random numbers come from a counter-based hash (PCG, O'Neill 2014) of (seed, pixel, sample):
deterministic for a seed, independent of tiling and thread count, and cheap inside the
compiled kernel. Computation runs in float32 (the geometry in pixel and millimetre units stays
well within its precision); compiled once per scene structure (target kinds) and image width.

Cost: proportional to pixels x samples per pixel x objects; see ``synth bench`` figures in the
README (million lens samples per second).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from synth import textures
from synth.scene import Shot

TILE_SAMPLES = 1 << 21  # lens samples per compiled call (about 2 M)


def _pcg(v):
    """PCG-RXS-M-XS 32-bit hash (uint32 -> uint32)."""
    state = v * jnp.uint32(747796405) + jnp.uint32(2891336453)
    word = ((state >> ((state >> jnp.uint32(28)) + jnp.uint32(4))) ^ state) * jnp.uint32(277803737)
    return (word >> jnp.uint32(22)) ^ word


def _unit(h):
    """uint32 hash -> float32 uniform in [0, 1)."""
    return (h >> jnp.uint32(8)).astype(jnp.float32) * jnp.float32(1.0 / (1 << 24))


def concentric_disk(a, b):
    """Map the unit square to the unit disk, preserving stratification (Shirley & Chiu 1997)."""
    a = 2.0 * a - 1.0
    b = 2.0 * b - 1.0
    use_a = jnp.abs(a) > jnp.abs(b)
    safe_a = jnp.where(a == 0, 1.0, a)
    safe_b = jnp.where(b == 0, 1.0, b)
    r = jnp.where(use_a, a, b)
    phi = jnp.where(use_a, (math.pi / 4) * (b / safe_a), (math.pi / 2) - (math.pi / 4) * (a / safe_b))
    return r * jnp.cos(phi), r * jnp.sin(phi)


def thin_lens_ray(pixel_x, pixel_y, lens_x_mm, lens_y_mm, cam):
    """Direction (dx, dy, 1) of the ray from a lens point through the pixel's focus-plane point.

    ``cam`` = (cx, cy, p/s, 1/D_s, A). A point of the ray at depth z is
    (lens_x + z dx, lens_y + z dy, z); at z = D_s every lens point of one pixel meets the
    chief ray's point ((x - cx) p D_s / s, (y - cy) p D_s / s).
    """
    cx, cy, scale, inv_focus = cam[0], cam[1], cam[2], cam[3]
    dx = (pixel_x - cx) * scale - lens_x_mm * inv_focus
    dy = (pixel_y - cy) * scale - lens_y_mm * inv_focus
    return dx, dy


def _pairing_prime(spp: int) -> int:
    for p in (7919, 7927, 7933, 7937, 7949):
        if spp % p:
            return p
    return 1


@partial(jax.jit, static_argnames=("structure", "width", "rows", "spp"))
def _render_rows(row0, cam, planes, rasters, background, seed, *, structure, width, rows, spp):
    """Mean radiance of ``rows`` image rows from ``row0``: array (rows, width)."""
    n_pix = rows * width
    pix = jnp.arange(n_pix, dtype=jnp.uint32)
    sample = jnp.arange(spp, dtype=jnp.uint32)
    py_i = (pix // jnp.uint32(width)).astype(jnp.float32) + row0.astype(jnp.float32)
    px_i = (pix % jnp.uint32(width)).astype(jnp.float32)
    global_pix = pix + row0.astype(jnp.uint32) * jnp.uint32(width)
    key = _pcg(global_pix ^ _pcg(seed.astype(jnp.uint32) + jnp.uint32(0x9E3779B9)))[:, None]
    counter = key ^ (sample[None, :] * jnp.uint32(0x85EBCA6B))
    h1 = _pcg(counter)
    h2 = _pcg(h1 ^ jnp.uint32(0x68E31DA4))
    h3 = _pcg(h2 ^ jnp.uint32(0xB5297A4D))
    h4 = _pcg(h3 ^ jnp.uint32(0x1B56C4E9))
    n = int(math.isqrt(spp))
    if n * n == spp:  # n x n strata over the pixel; the lens strata paired by a per-pixel permutation
        sx = (sample % jnp.uint32(n)).astype(jnp.float32)[None, :]
        sy = (sample // jnp.uint32(n)).astype(jnp.float32)[None, :]
        jx, jy = (sx + _unit(h1)) / n, (sy + _unit(h2)) / n
        lens_stratum = (sample[None, :] * jnp.uint32(_pairing_prime(spp)) + (key % jnp.uint32(spp))) % jnp.uint32(spp)
        lx_u = ((lens_stratum % jnp.uint32(n)).astype(jnp.float32) + _unit(h3)) / n
        ly_u = ((lens_stratum // jnp.uint32(n)).astype(jnp.float32) + _unit(h4)) / n
    else:  # 1-D strata
        jx = (sample.astype(jnp.float32)[None, :] + _unit(h1)) / spp
        jy = _unit(h2)
        lx_u, ly_u = _unit(h3), _unit(h4)
    pixel_x = px_i[:, None] + jx - 0.5
    pixel_y = py_i[:, None] + jy - 0.5
    dxu, dyu = concentric_disk(lx_u, ly_u)
    radius = 0.5 * cam[4]
    lens_x, lens_y = radius * dxu, radius * dyu
    dx, dy = thin_lens_ray(pixel_x, pixel_y, lens_x, lens_y, cam)

    value = jnp.full(dx.shape, background, jnp.float32)
    nearest = jnp.full(dx.shape, jnp.inf, jnp.float32)
    for k, static in enumerate(structure):
        c, ex, ey, nrm = planes[k, 0:3], planes[k, 3:6], planes[k, 6:9], planes[k, 9:12]
        denom = dx * nrm[0] + dy * nrm[1] + nrm[2]
        num = (c[0] - lens_x) * nrm[0] + (c[1] - lens_y) * nrm[1] + c[2] * nrm[2]
        safe = jnp.where(jnp.abs(denom) > 1e-12, denom, 1.0)
        z = num / safe  # the ray parameter is the depth
        hx, hy = lens_x + z * dx - c[0], lens_y + z * dy - c[1]
        hz = z - c[2]
        u = hx * ex[0] + hy * ex[1] + hz * ex[2]
        v = hx * ey[0] + hy * ey[1] + hz * ey[2]
        hit = (jnp.abs(denom) > 1e-12) & (z > 0) & (z < nearest) & textures.inside(static, u, v)
        value = jnp.where(hit, textures.evaluate(static, rasters[k], u, v), value)
        nearest = jnp.where(hit, z, nearest)
    return value.mean(axis=1).reshape(rows, width)


def scene_arrays(shot: Shot):
    """Per-object plane arrays (centre, x axis, y axis, normal; camera frame, mm) and textures."""
    structure, rasters, planes = [], [], []
    for obj in shot.objects:
        tex = textures.texture(obj.target)
        structure.append(tex.static)
        rasters.append(jnp.asarray(tex.raster, jnp.float32))
        R, t = obj.pose.R_cam_target, obj.pose.t_cam_target
        planes.append(np.concatenate([t, R[:, 0], R[:, 1], R[:, 2]]))
    planes_arr = jnp.asarray(np.array(planes, np.float32).reshape(-1, 12))
    return tuple(structure), tuple(rasters), planes_arr


def camera_array(shot: Shot):
    cam = shot.camera
    cx, cy = cam.principal_point_px
    return jnp.asarray([cx, cy, cam.pixel_pitch_mm / cam.sensor_distance_mm, cam.inverse_focus_distance,
                        cam.aperture_diameter_mm], jnp.float32)


def render_raytrace(shot: Shot, background: float, spp: int, seed: int,
                    progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Render one shot by ray tracing; returns linear radiance, float32 (height, width).

    ``progress(n)`` is called with the number of rows finished after each tile.
    """
    cam = shot.camera
    W, H = cam.width_px, cam.height_px
    rows = max(1, min(H, TILE_SAMPLES // max(1, W * spp)))
    structure, rasters, planes = scene_arrays(shot)
    cam_arr = camera_array(shot)
    out = np.empty((H, W), np.float32)
    for r0 in range(0, H, rows):
        block = _render_rows(jnp.int32(r0), cam_arr, planes, rasters, jnp.float32(background), jnp.uint32(seed),
                             structure=structure, width=W, rows=rows, spp=spp)
        take = min(rows, H - r0)
        out[r0:r0 + take] = np.asarray(block)[:take]
        if progress is not None:
            progress(take)
    return out
