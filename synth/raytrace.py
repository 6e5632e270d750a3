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
from synth.effects.aperture import sample as aperture_sample
from synth.scene import Shot

TILE_SAMPLES = 1 << 20  # lens samples per compiled call: measured fastest on 2 cores (synth bench)


def _pcg(v):
    """PCG-RXS-M-XS 32-bit hash (uint32 -> uint32)."""
    state = v * jnp.uint32(747796405) + jnp.uint32(2891336453)
    word = ((state >> ((state >> jnp.uint32(28)) + jnp.uint32(4))) ^ state) * jnp.uint32(277803737)
    return (word >> jnp.uint32(22)) ^ word


def _unit16(h):
    """Low 16 bits of a uint32 hash -> float32 uniform in [0, 1), offset to the bin centre."""
    return ((h & jnp.uint32(0xFFFF)).astype(jnp.float32) + 0.5) * jnp.float32(1.0 / (1 << 16))


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
                                               (ddx / norm, ddy / norm, -ddz / norm), jnp)
    passed = passed & (dz > 1e-6)
    safe = jnp.where(passed, dz, 1.0)
    # Scene frame: depth = z_ep - z = z_ep - (z_last - z'), direction per unit depth (dx/dz', dy/dz').
    depth0 = z_ep - (z_last - zr)
    sx, sy = dx / safe, dy / safe
    return x - depth0 * sx, y - depth0 * sy, sx, sy, passed


def _permute(i, key, mask: int):
    """A pseudo-random permutation of [0, mask] (mask = 2^k - 1), one per key.

    Kensler, "Correlated Multi-Jittered Sampling" (Pixar Technical Memo 13-01, 2013), power-of-two
    case: every step is a bijection of the low k bits, so the result is a permutation.
    """
    u = jnp.uint32
    m = u(mask)
    i = i ^ key
    i = i * u(0xE170893D)
    i = i ^ (key >> u(16))
    i = i ^ ((i & m) >> u(4))
    i = i ^ (key >> u(8))
    i = i * u(0x0929EB3F)
    i = i ^ (key >> u(23))
    i = i ^ ((i & m) >> u(1))
    i = i * (u(1) | (key >> u(27)))
    i = i * u(0x6935FA69)
    i = i ^ ((i & m) >> u(11))
    i = i * u(0x74DCB303)
    i = i ^ ((i & m) >> u(2))
    i = i * u(0x9E501CC3)
    i = i ^ ((i & m) >> u(2))
    i = i * u(0xC860A3DF)
    i = i & m
    i = i ^ (i >> u(5))
    return (i + key) & m


@partial(jax.jit, static_argnames=("structure", "width", "rows", "spp", "aperture", "front_stop", "compound",
                                   "quadrants"))
def _render_rows(row0, cam, planes, rasters, background, seed, warp=None, *, structure, width, rows, spp,
                 aperture=("circle",), front_stop=None, compound=None, quadrants=False):
    """Mean radiance of ``rows`` image rows from ``row0``: array (rows, width); with
    ``quadrants`` (``spp`` an even square, see :func:`quadrant_spp`) also the mean over each
    quarter of every pixel, (2 rows, 2 width): the same samples, whose n x n pixel strata fall
    into the quarters n/2 x n/2 each.

    ``aperture`` is ``synth.effects.aperture.Aperture.static``; ``front_stop`` is None or
    (distance_mm, radius_mm) of the stop that clips the pupil off axis (optical vignetting,
    ``synth.effects.vignetting``): rays it blocks carry no light. ``warp`` is None or, per pixel
    of these rows, (u, v, du/dx, du/dy, dv/dx, dv/dy): the pinhole position whose image a lens
    distortion moves to the pixel centre and the local derivatives, so that each sample of the
    distorted pixel traces its own undistorted ray (exact distortion, ``synth.effects.distortion``).
    """
    n_pix = rows * width
    pix = jnp.arange(n_pix, dtype=jnp.uint32)
    sample = jnp.arange(spp, dtype=jnp.uint32)
    py_i = (pix // jnp.uint32(width)).astype(jnp.float32) + row0.astype(jnp.float32)
    px_i = (pix % jnp.uint32(width)).astype(jnp.float32)
    global_pix = pix + row0.astype(jnp.uint32) * jnp.uint32(width)
    key = _pcg(global_pix ^ _pcg(seed.astype(jnp.uint32) + jnp.uint32(0x9E3779B9)))[:, None]
    counter = key ^ (sample[None, :] * jnp.uint32(0x85EBCA6B))
    # Two hashes give four 16-bit uniforms: 1/65536 of a stratum is far below any effect here.
    ha = _pcg(counter)
    hb = _pcg(ha ^ jnp.uint32(0x68E31DA4))
    u1, u2 = _unit16(ha), _unit16(ha >> jnp.uint32(16))
    u3, u4 = _unit16(hb), _unit16(hb >> jnp.uint32(16))
    n = int(math.isqrt(spp))
    if n * n == spp:  # n x n strata over the pixel
        sx = (sample % jnp.uint32(n)).astype(jnp.float32)[None, :]
        sy = (sample // jnp.uint32(n)).astype(jnp.float32)[None, :]
        jx, jy = (sx + u1) / n, (sy + u2) / n
        if spp & (spp - 1) == 0:
            # n x n lens strata, paired with the pixel strata by a per-pixel random permutation
            # (a fixed pairing would correlate pixel and lens positions and add variance).
            lens_stratum = _permute(sample[None, :], key, spp - 1)
            lx_u = ((lens_stratum % jnp.uint32(n)).astype(jnp.float32) + u3) / n
            ly_u = ((lens_stratum // jnp.uint32(n)).astype(jnp.float32) + u4) / n
        else:
            lx_u, ly_u = u3, u4
    else:  # 1-D strata
        jx = (sample.astype(jnp.float32)[None, :] + u1) / spp
        jy = u2
        lx_u, ly_u = u3, u4
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
    mean = value.mean(axis=1).reshape(rows, width)
    if not quadrants:
        return mean
    h = n // 2  # value[p, sy * n + sx] -> [p, qy, sy', qx, sx'] with sy = qy h + sy'
    quarter = value.reshape(rows, width, 2, h, 2, h).mean(axis=(3, 5))  # (rows, width, qy, qx)
    return mean, quarter.transpose(0, 2, 1, 3).reshape(2 * rows, 2 * width)


def quadrant_spp(spp: int) -> bool:
    """Whether ``spp`` samples stratify each quarter of a pixel alike (an even square: 4, 16,
    64, 256, ...), so that the ray tracer can return the image at twice the resolution."""
    n = math.isqrt(spp)
    return n * n == spp and n % 2 == 0


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
    if getattr(cam, "prescription", None) is None:
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


#: Working memory per lens sample inside one compiled tile (rays, weights, hits; float32).
BYTES_PER_SAMPLE = 96


def raytrace_bytes(width_px: int, spp: int) -> float:
    """Peak memory (bytes) of one ray-tracing tile: at least one image row of ``spp`` samples."""
    return float(BYTES_PER_SAMPLE) * max(TILE_SAMPLES, width_px * spp)


def render_raytrace(shot: Shot, background: float, spp: int, seed: int,
                    progress: Callable[[int], None] | None = None, *, camera=None,
                    aperture: tuple = ("circle",), front_stop: tuple[float, float] | None = None,
                    warp: np.ndarray | None = None, fine: bool = False):
    """Render one shot by ray tracing; returns linear radiance, float32 (height, width).

    ``progress(n)`` is called with the number of rows finished after each tile. ``camera``
    replaces the shot's camera (one colour channel's, under chromatic aberration);
    ``aperture``, ``front_stop`` and ``warp`` (here (height, width, 6)) as for ``_render_rows``.
    ``fine`` (where :func:`quadrant_spp`): returns (image, fine image) with the fine image at
    twice the resolution, each quarter pixel the mean of its own samples (no extra rays); its
    2 x 2 means are the image. Diffraction filters that one, before the pixels integrate it.
    """
    if fine and not quadrant_spp(spp):
        raise ValueError(f"a fine image needs an even square number of samples per pixel, not {spp}")
    cam = camera if camera is not None else shot.camera
    W, H = cam.width_px, cam.height_px
    rows = max(1, min(H, TILE_SAMPLES // max(1, W * spp)))
    structure, rasters, planes = scene_arrays(shot)
    cam_arr = camera_array(cam)
    compound = None
    if getattr(cam, "prescription", None) is not None:
        from synth.lens import reverse

        compound = reverse(cam.stopped)
    out = np.empty((H, W), np.float32)
    out_fine = np.empty((2 * H, 2 * W), np.float32) if fine else None
    if warp is not None:  # padded to whole tiles, flattened per pixel
        pad = (-H) % rows
        warp_rows = np.concatenate([warp, np.repeat(warp[-1:], pad, axis=0)]).astype(np.float32).reshape(-1, W, 6)
    for r0 in range(0, H, rows):
        tile_warp = None if warp is None else jnp.asarray(warp_rows[r0:r0 + rows].reshape(-1, 6))
        block = _render_rows(jnp.int32(r0), cam_arr, planes, rasters, jnp.float32(background), jnp.uint32(seed),
                             tile_warp,
                             structure=structure, width=W, rows=rows, spp=spp, aperture=aperture,
                             front_stop=front_stop, compound=compound, quadrants=fine)
        take = min(rows, H - r0)
        if fine:
            block, quarter = block
            out_fine[2 * r0:2 * (r0 + take)] = np.asarray(quarter)[:2 * take]
        out[r0:r0 + take] = np.asarray(block)[:take]
        if progress is not None:
            progress(take)
    return (out, out_fine) if fine else out
