"""``raytrace``: thin-lens Monte-Carlo ray tracing of planar scenes.

For every pixel sample (the course's "ray tracing for defocus blur"):

1. a point in the pixel footprint (box filter: pixel integration; stratified, one sample per
   cell of an n x n grid when spp = n^2);
2. a point on the aperture disk (concentric-disk mapping, Shirley & Chiu 1997);
3. the ray from that lens point through the point of the plane of focus that the pixel's
   chief ray hits (``synth.geometry`` gives the formulas; focus at infinity is exact);
4. the nearest intersection with the scene's planes (so occlusion is exact);
5. the texture at the hit (point-sampled; the Monte-Carlo average over pixel and aperture
   samples is the filter), or the background when nothing is hit.

Exact for every planar scene up to Monte-Carlo noise, which falls like 1/sqrt(spp) or faster.

The four coordinates of a sample (pixel x, y; lens x, y) are randomised quasi-Monte Carlo: the
first spp points of a 4-D Sobol sequence (:func:`sobol_16bit`), the same for every pixel, each
pixel's copy given a random digital shift (its coordinates' 16 bits XORed with a mask per pixel
and dimension, Kollig & Keller 2002), so that each sample is uniform on its own and the pixel's
set keeps the sequence's joint stratification. The masks come from a counter-based hash (PCG,
O'Neill 2014) of (seed, pixel): deterministic for a seed, independent of tiling and thread
count. Against per-sample hashed jitter with the lens strata randomly permuted per pixel, on the
demo's fronto-parallel shot: RMS error 21-24 % lower at 4-256 spp, and 1.5x the samples per
second (per-sample hashes would be most of the arithmetic, which XLA repeats in each fused
loop). Computation runs in float32 (the geometry in pixel and millimetre units stays well within
its precision); compiled once per scene structure (target kinds) and image width, and kept as
an executable (``lensfit.runtime.jaxcache``) where the command-line tools keep a store.

Cost: proportional to the pixels traced x samples per pixel x objects. A pixel whose every ray
meets one region of constant reflectance (inside a board's square, its margin, a uniform patch,
the background) has that value as its exact mean and is not sampled (``synth.flat``, decided
per 4 px block from the block's corners and the aperture; a thin lens without front stop, from
4 samples per pixel): 5-35 % of a demo shot's pixels are traced, and the
images are the same (to the byte on the demo's 16-bit PNGs at 16, 64 and 256 spp; where the
cell image feeds diffraction, a constant cell is its exact value where the traced
one was a float32 mean: 1 DN in 0.2 % of a 256-spp stack's pixels). Tiles are lists of the
pixels to trace. ``synth bench`` measures it (million lens samples
per second with every pixel traced, and seconds as rendered).
"""

from __future__ import annotations

import math
from functools import lru_cache, partial
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.runtime import jaxcache
from synth import flat, textures
from synth.effects.aperture import sample as aperture_sample
from synth.scene import Shot

TILE_SAMPLES = 1 << 20  # lens samples per compiled call: measured fastest on 2 cores (synth bench)
#: The modules whose source defines the compiled tracer of a thin lens (a change traces it afresh;
#: lensfit.runtime.jaxcache keeps its executable where the command-line tools switched the store on: a new
#: process then loads it instead of tracing and lowering it for JAX's persistent cache).
AOT_MODULES = ("synth.raytrace", "synth.textures", "synth.effects.aperture", "synth.lens.prescription",
               "lensfit.optics.checks")


def _pcg(v):
    """PCG-RXS-M-XS 32-bit hash (uint32 -> uint32)."""
    state = v * jnp.uint32(747796405) + jnp.uint32(2891336453)
    word = ((state >> ((state >> jnp.uint32(28)) + jnp.uint32(4))) ^ state) * jnp.uint32(277803737)
    return (word >> jnp.uint32(22)) ^ word


def _cos_sin_quarter(psi):
    """cos and sin for |psi| <= pi/4 by their Taylor series (error < 4e-7, below float32 needs here)."""
    p2 = psi * psi
    sin = psi * (1.0 + p2 * (-1.0 / 6 + p2 * (1.0 / 120 + p2 * (-1.0 / 5040))))
    cos = 1.0 + p2 * (-0.5 + p2 * (1.0 / 24 + p2 * (-1.0 / 720 + p2 * (1.0 / 40320))))
    return cos, sin


def concentric_disk(a, b):
    """Map the unit square to the unit disk, preserving stratification (Shirley & Chiu 1997).

    The angle is ``pi/4 * b/a`` (or ``pi/2 - pi/4 * a/b``), always within a quarter turn of an
    axis, so cos and sin come from short series instead of general trigonometry.
    """
    a = 2.0 * a - 1.0
    b = 2.0 * b - 1.0
    use_a = jnp.abs(a) > jnp.abs(b)
    r = jnp.where(use_a, a, b)
    safe_r = jnp.where(r == 0, 1.0, r)
    psi = (math.pi / 4) * jnp.where(use_a, b, a) / safe_r
    c, s = _cos_sin_quarter(psi)
    # use_a: phi = psi -> (r cos, r sin); else phi = pi/2 - psi -> (r sin, r cos).
    return r * jnp.where(use_a, c, s), r * jnp.where(use_a, s, c)


def thin_lens_ray(pixel_x, pixel_y, lens_x_mm, lens_y_mm, cam):
    """Direction (dx, dy, 1) of the ray from a lens point through the pixel's focus-plane point.

    ``cam`` = (cx, cy, p/s, 1/D_s, A). A point of the ray at depth z is
    (lens_x + z dx, lens_y + z dy, z); at z = D_s every lens point of one pixel meets the
    chief ray's point ((x - cx) p D_s / s, (y - cy) p D_s / s).
    """
    cx, cy, scale, inverse_focus_distance_per_mm = cam[0], cam[1], cam[2], cam[3]
    dx = (pixel_x - cx) * scale - lens_x_mm * inverse_focus_distance_per_mm
    dy = (pixel_y - cy) * scale - lens_y_mm * inverse_focus_distance_per_mm
    return dx, dy


def compound_lens_ray(pixel_x, pixel_y, ux, uy, cam, reversed_rx):
    """A ray from a sensor point through a compound lens into the scene (pbrt's RealisticCamera:
    trace from the sensor through the rear element).

    The sensor point is the pixel position (the image is inverted: pixel +x sees object +x);
    the ray aims at the point ``(ux, uy)`` of the unit disk scaled to the sampling radius on the
    exit pupil's plane, and is traced exactly through ``reversed_rx`` (``synth.lens.reverse``).
    ``cam`` = (cx, cy, pitch, 1/X, A, sensor_z, entrance_pupil_z, exit_pupil_z, sample radius,
    brightness scale, last vertex z), lens coordinates (first vertex at 0, +z to the sensor).
    Returns the ray in the renderer's form (its point at depth 0 from the entrance pupil and its
    direction per unit depth) and whether it passed every aperture.
    """
    from synth.lens import trace

    pitch, z_sensor, z_ep, z_xp, r_s, z_last = cam[2], cam[5], cam[6], cam[7], cam[8], cam[10]
    xs = -(pixel_x - cam[0]) * pitch
    ys = -(pixel_y - cam[1]) * pitch
    tx, ty = r_s * ux, r_s * uy
    ddx, ddy, ddz = tx - xs, ty - ys, jnp.broadcast_to(z_xp - z_sensor, xs.shape)  # towards the lens (-z)
    norm = jnp.sqrt(ddx * ddx + ddy * ddy + ddz * ddz)
    # Reversed lens frame: z' = z_last - z, so the ray travels +z'.
    (x, y, zr), (dx, dy, dz), passed, _ = trace(reversed_rx, (xs, ys, jnp.broadcast_to(z_last - z_sensor, xs.shape)),
                                               (ddx / norm, ddy / norm, -ddz / norm))
    passed = passed & (dz > 1e-6)
    safe = jnp.where(passed, dz, 1.0)
    # Scene frame: depth = z_ep - z = z_ep - (z_last - z'), direction per unit depth (dx/dz', dy/dz').
    depth0 = z_ep - (z_last - zr)
    sx, sy = dx / safe, dy / safe
    return x - depth0 * sx, y - depth0 * sy, sx, sy, passed


#: Sobol dimensions 2-4 (degree s, coefficients a, initial direction numbers m; Joe & Kuo 2008,
#: as scipy.stats.qmc.Sobol); dimension 1 is van der Corput's.
SOBOL_JOE_KUO = ((1, 0, (1,)), (2, 1, (1, 3)), (3, 1, (1, 3, 1)))


def sobol_16bit(m: int) -> np.ndarray:
    """The first 2^m points (m <= 16) of the 4-D Sobol sequence in Gray-code order, as 16-bit
    integers (uint32, the coordinates times 2^16): scipy.stats.qmc.Sobol's unscrambled points,
    computed here because importing scipy.stats costs a renderer process about half a second."""
    bits = 16
    if not 0 <= m <= bits:
        raise ValueError(f"sobol_16bit: m = {m}, needs 0 <= m <= {bits}")
    dirs = [[1 << (bits - k) for k in range(1, bits + 1)]]
    for s, a, m0 in SOBOL_JOE_KUO:
        mk = list(m0)
        for k in range(s, bits):
            new = mk[k - s] ^ (mk[k - s] << s)
            for j in range(1, s):
                if (a >> (s - 1 - j)) & 1:
                    new ^= mk[k - j] << j
            mk.append(new)
        dirs.append([mk[k] << (bits - 1 - k) for k in range(bits)])
    index = np.arange(1 << m, dtype=np.uint32)
    gray = index ^ (index >> np.uint32(1))
    out = np.zeros((1 << m, 4), np.uint32)
    for j, v in enumerate(dirs):
        for k in range(m):
            out[:, j] ^= np.where((gray >> np.uint32(k)) & np.uint32(1), np.uint32(v[k]), np.uint32(0))
    return out


@lru_cache(maxsize=None)
def sample_table(spp: int) -> np.ndarray:
    """The samples of one pixel before its digital shift: (spp, 4) uint32, 16-bit coordinates
    (pixel x, pixel y, lens x, lens y) of the first spp 4-D Sobol points. Where spp = n^2, the
    renderer puts sample k in cell (k % n, k // n) of an n x n grid over the pixel (as
    :func:`cell_factor` needs) and the pixel coordinates place it within its cell; where n is
    a power of 2 too, the pixel coordinates of the Sobol points (a (0, m, 2)-net: one point per
    cell) are sorted by cell and replaced by their positions within it, so that the cells keep
    the sequence's joint stratification with the lens coordinates."""
    if not 1 <= spp <= 1 << 16:
        raise ValueError(f"samples per pixel: {spp}, needs 1 to 65536")
    pts = sobol_16bit(max(0, math.ceil(math.log2(spp))))[:spp]
    n = math.isqrt(spp)
    if n * n == spp and spp & (spp - 1) == 0 and spp > 1:
        shift = 16 - int(math.log2(n))  # the top log2(n) bits name the cell
        cell = (pts[:, 0] >> shift) + n * (pts[:, 1] >> shift)
        pts = pts[np.argsort(cell, kind="stable")]
        low = np.uint32((1 << shift) - 1)
        pts[:, :2] = (pts[:, :2] & low) << np.uint32(16 - shift)
    pts.setflags(write=False)  # cached: shared by every call
    return pts


@partial(jax.jit, static_argnames=("structure", "width", "spp", "aperture", "front_stop", "compound", "cells"))
def _render_pixels(pixels, cam, planes, rasters, background, seed, warp=None, *, structure, width, spp,
                   aperture=("circle",), front_stop=None, compound=None, cells=1):
    """Mean radiance of the pixels ``pixels`` (uint32 indices ``row * width + column``): array
    (count,); with ``cells`` k above 1 (dividing n, ``spp = n^2``: :func:`cell_factor`) also the
    mean over each of the k x k cells of every pixel, (count, k, k) (cell row, cell column): the
    same samples, whose n x n pixel strata fall into the cells n/k x n/k each.

    ``aperture`` is ``synth.effects.aperture.Aperture.static``; ``front_stop`` is None or
    (distance_mm, radius_mm) of the stop that clips the pupil off axis (optical vignetting,
    ``synth.effects.vignetting``): rays it blocks carry no light. ``warp`` is None or, per pixel,
    (u, v, du/dx, du/dy, dv/dx, dv/dy): the pinhole position whose image a lens distortion moves
    to the pixel centre and the local derivatives, so that each sample of the distorted pixel
    traces its own undistorted ray (exact distortion, ``synth.effects.distortion``).
    """
    sample = jnp.arange(spp, dtype=jnp.uint32)
    global_pix = pixels.astype(jnp.uint32)
    py_i = (global_pix // jnp.uint32(width)).astype(jnp.float32)
    px_i = (global_pix % jnp.uint32(width)).astype(jnp.float32)
    key = _pcg(global_pix ^ _pcg(seed.astype(jnp.uint32) + jnp.uint32(0x9E3779B9)))[:, None]
    # The pixel's digital shift: four 16-bit masks from two hashes per pixel (sample_table).
    key_b = _pcg(key ^ jnp.uint32(0x68E31DA4))
    masks = (key & jnp.uint32(0xFFFF), key >> jnp.uint32(16), key_b & jnp.uint32(0xFFFF), key_b >> jnp.uint32(16))
    table = sample_table(spp)

    def coordinate(j):  # in [0, 1), at the centre of its 1/65536 bin
        return (((jnp.asarray(table[:, j])[None, :] ^ masks[j]).astype(jnp.float32) + 0.5)
                * jnp.float32(1.0 / (1 << 16)))
    n = int(math.isqrt(spp))
    if n * n == spp:  # sample k in cell (k % n, k // n) of the pixel
        sx = (sample % jnp.uint32(n)).astype(jnp.float32)[None, :]
        sy = (sample // jnp.uint32(n)).astype(jnp.float32)[None, :]
        jx, jy = (sx + coordinate(0)) / n, (sy + coordinate(1)) / n
    else:
        jx, jy = coordinate(0), coordinate(1)
    lx_u, ly_u = coordinate(2), coordinate(3)
    if warp is None:
        pixel_x = px_i[:, None] + jx - 0.5
        pixel_y = py_i[:, None] + jy - 0.5
    else:  # the sample's offset in the distorted pixel, carried to the pinhole image
        ox, oy = jx - 0.5, jy - 0.5
        pixel_x = warp[:, 0:1] + warp[:, 2:3] * ox + warp[:, 3:4] * oy
        pixel_y = warp[:, 1:2] + warp[:, 4:5] * ox + warp[:, 5:6] * oy
    dxu, dyu = aperture_sample(aperture, lx_u, ly_u, concentric_disk)
    if compound is None:
        radius = 0.5 * cam[4]
        lens_x, lens_y = radius * dxu, radius * dyu
        dx, dy = thin_lens_ray(pixel_x, pixel_y, lens_x, lens_y, cam)
        lens_passed = None
    else:
        lens_x, lens_y, dx, dy, lens_passed = compound_lens_ray(pixel_x, pixel_y, dxu, dyu, cam, compound)

    value = jnp.full(dx.shape, background, jnp.float32)
    if front_stop is not None:
        L, rad = front_stop
        bx, by = lens_x + L * dx, lens_y + L * dy
        passed = bx * bx + by * by <= rad * rad
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
    if front_stop is not None:
        value = jnp.where(passed, value, 0.0)
    if lens_passed is not None:  # blocked by a clear aperture of the compound lens: no light
        value = jnp.where(lens_passed, value, 0.0) * cam[9]
    mean = value.mean(axis=1)
    if cells <= 1:
        return mean
    h = n // cells  # value[p, sy * n + sx] -> [p, qy, sy', qx, sx'] with sy = qy h + sy'
    return mean, value.reshape(-1, cells, h, cells, h).mean(axis=(2, 4))  # (count, qy, qx)


def cell_factor(spp: int) -> int:
    """How many times the resolution (per axis) the ray tracer can return its image at from
    ``spp`` samples per pixel, each cell the mean of whole strata of the pixel's n x n
    (``spp = n^2``): 8, 4 or 2, the largest that divides n (16 spp: 4; 64 and 256 spp: 8), else 1.
    Each stratum's sample is uniform within it, so every cell's mean is an unbiased estimate of
    the irradiance integrated over that cell, one sample each or more."""
    n = math.isqrt(spp)
    if n * n != spp:
        return 1
    return next((k for k in (8, 4, 2) if n % k == 0), 1)


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


def camera_array(cam):
    cx, cy = cam.principal_point_px
    if cam.prescription is None:
        return jnp.asarray([cx, cy, cam.pixel_pitch_mm / cam.sensor_distance_mm, cam.inverse_focus_distance_per_mm,
                            cam.aperture_diameter_mm], jnp.float32)
    return jnp.asarray(compound_camera_values(cam), jnp.float32)


#: The exit pupil is sampled over this multiple of its radius: off axis the pupil shifts and
#: narrows (cat's eye), and rays aimed beyond what passes are blocked by the lens itself.
PUPIL_SAMPLING_MARGIN = 1.25


#: Brightness of an unvignetted image point of a white target through a compound lens: the
#: fraction of exit-pupil samples that pass varies from pixel to pixel by a few per cent at
#: tens of samples, and a mean of 1 would clip those above it.
COMPOUND_WHITE = 0.9


def compound_camera_values(cam) -> list[float]:
    """The kernel's numbers for a ``CompoundLensCamera`` (see :func:`compound_lens_ray`); the
    brightness scale puts an unvignetted image point at ``COMPOUND_WHITE`` times the scene's
    radiance: that over the fraction of sampled rays that pass on the axis (float64 trace)."""
    from synth.lens import disk_grid, reverse, trace

    para = cam.paraxial
    cx, cy = cam.principal_point_px
    r_s = PUPIL_SAMPLING_MARGIN * 0.5 * para.exit_pupil_diameter_mm
    z_last = float(cam.stopped.vertices_mm()[-1])
    gx, gy = disk_grid(256)
    tx, ty = r_s * gx, r_s * gy
    dz = para.exit_pupil_z_mm - cam.sensor_z_mm
    norm = np.sqrt(tx**2 + ty**2 + dz**2)
    z0 = np.full(tx.shape, z_last - cam.sensor_z_mm)
    _, _, passed, _ = trace(reverse(cam.stopped), (np.zeros_like(tx), np.zeros_like(tx), z0),
                            (tx / norm, ty / norm, -dz / norm))
    scale = COMPOUND_WHITE / max(float(passed.mean()), 1e-6)
    return [cx, cy, cam.pixel_pitch_mm, cam.inverse_focus_distance_per_mm, cam.aperture_diameter_mm, cam.sensor_z_mm,
            cam.scene_origin_z_mm, para.exit_pupil_z_mm, r_s, scale, z_last]


def tile_pixels(width_px: int, height_px: int, spp: int) -> int:
    """Pixels per compiled call: ``TILE_SAMPLES`` lens samples (at least one pixel), no more
    than the image holds. Two tiles are in flight (:func:`render_raytrace`), each about 96
    bytes a lens sample (rays, weights, hits; float32): 0.2 GB at most, at 65 536 spp (the
    sampler's limit), whatever the image's size."""
    return max(1, min(width_px * height_px, TILE_SAMPLES // max(1, spp)))


def render_raytrace(shot: Shot, background: float, spp: int, seed: int,
                    progress: Callable[[int], None] | None = None, *, camera=None,
                    aperture: tuple = ("circle",), front_stop: tuple[float, float] | None = None,
                    warp: np.ndarray | None = None, fine: int = 1, constant_regions: bool = True):
    """Render one shot by ray tracing; returns linear radiance, float32 (height, width).

    ``progress(n)`` is called with the number of rows finished (in proportion to the pixels
    traced) after each tile. ``camera`` replaces the shot's camera (one colour channel's, under
    chromatic aberration); ``aperture``, ``front_stop`` and ``warp`` (here (height, width, 6)) as
    for ``_render_pixels``. ``fine`` (a factor k above 1 that divides n, ``spp = n^2``): returns
    (image, fine image) with the fine image at k times the resolution, each cell the mean of its
    own samples (no extra rays); its k x k means are the image. Diffraction filters that one,
    before the pixels integrate it. ``constant_regions``: pixels whose every ray meets one region of
    constant reflectance (or nothing) take that value without being sampled
    (:mod:`synth.flat`; a thin lens without front stop, from ``flat.MIN_SPP`` samples per
    pixel); the traced pixels are the same either way.
    """
    k_fine = int(fine)
    n = math.isqrt(spp)
    if k_fine > 1 and (n * n != spp or n % k_fine):
        raise ValueError(f"a fine image at {k_fine} times the resolution needs n x n samples per pixel with n a "
                         f"multiple of {k_fine}, not {spp}")
    cam = camera if camera is not None else shot.camera
    W, H = cam.width_px, cam.height_px
    structure, rasters, planes = scene_arrays(shot)
    cam_arr = camera_array(cam)
    compound = None
    if cam.prescription is not None:
        from synth.lens import reverse

        compound = reverse(cam.stopped)
    if constant_regions and compound is None and front_stop is None and spp >= flat.MIN_SPP:
        out = flat.constant_pixels(structure, rasters, planes, cam_arr, W, H, background, aperture, warp)
        todo = np.flatnonzero(np.isnan(out)).astype(np.uint32)  # the pixels to trace
    else:
        out, todo = np.full((H, W), np.nan, np.float32), None  # every pixel, in order
    total = H * W if todo is None else len(todo)
    out_fine = np.repeat(np.repeat(out, k_fine, axis=0), k_fine, axis=1) if k_fine > 1 else None
    count = tile_pixels(W, H, spp)
    warp_flat = None if warp is None else np.ascontiguousarray(warp, np.float32).reshape(-1, 6)
    static = {"structure": structure, "width": W, "spp": spp, "aperture": aperture,
              "front_stop": front_stop, "compound": compound, "cells": k_fine}

    def tile(k0):
        """The pixels of the tile from the ``k0``-th to trace."""
        if todo is None:
            return np.arange(k0, min(k0 + count, total), dtype=np.uint32)
        return todo[k0:k0 + count]

    def dispatch(k0):
        pixels = tile(k0)
        if len(pixels) < count:  # the last tile padded with its last pixel (traced, not kept)
            pixels = np.concatenate([pixels, np.full(count - len(pixels), pixels[-1], np.uint32)])
        tile_warp = None if warp_flat is None else warp_flat[pixels]
        # numpy scalars: a jnp scalar is an operation of its own (0.2 ms each, three per tile)
        args = (pixels, cam_arr, planes, rasters, np.float32(background), np.uint32(seed), tile_warp)
        if compound is None:  # kept compiled (lensfit.runtime.jaxcache) where the command-line tools keep a store
            return jaxcache.call("raytrace", _render_pixels, args, static, AOT_MODULES, kernels=False)
        return _render_pixels(*args, **static)  # (a lens prescription is no file name's part)

    # The next tile is dispatched before this one's result is waited for, so that the Python work
    # between tiles overlaps the tracing (demo at 16 / 64 spp: 1.45 -> 1.12 s, 3.30 -> 2.95 s a
    # stack, with the numpy scalars); two tiles' memory at most (tile_pixels).
    starts = list(range(0, total, count))
    out = np.ascontiguousarray(out)
    flat_out = out.reshape(-1)  # a view (contiguous): the tiles write into out
    fine_view = out_fine.reshape(H, k_fine, W, k_fine) if k_fine > 1 else None
    reported = 0
    pending = dispatch(starts[0]) if starts else None
    for k, k0 in enumerate(starts):
        block = pending
        pending = dispatch(starts[k + 1]) if k + 1 < len(starts) else None
        pixels = tile(k0)
        take = len(pixels)
        where = slice(k0, k0 + take) if todo is None else pixels
        if k_fine > 1:
            block, quarter = block
            fine_view[pixels // W, :, pixels % W, :] = np.asarray(quarter)[:take]
        flat_out[where] = np.asarray(block)[:take]
        if progress is not None:
            done = (H * (k0 + take)) // total
            progress(done - reported)
            reported = done
    if progress is not None and reported < H:
        progress(H - reported)
    return (out, out_fine) if k_fine > 1 else out
