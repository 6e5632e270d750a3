"""Target textures: reflectance as a function of position on the target plane.

Each target is a function ``value(x_mm, y_mm)`` in the target's own frame (origin at the
centre, x along the width, y along the height, down). Boards, slanted edges and stars are
evaluated analytically (their edges are exact lines); a ChArUco board is OpenCV's own
rendering, held as a raster with a whole number of texels per square *and* per marker cell
(``lensfit.calibration.targets.charuco_texels_per_square``) and looked up with nearest-neighbour, so the texture *is* a piecewise-constant function whose square edges are
exactly where the board says; image files are looked up bilinearly. Anti-aliasing is not done
here: both render methods integrate over the pixel footprint (and the aperture), which is the
proper filter for a point-sampled texture.

A texture is split into a hashable ``static`` part (kind and parameters, which select the
compiled code) and a ``raster`` array (data), so that shots with the same targets reuse one
compiled kernel.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from synth.scene import TargetSpec

CHARUCO_TEXELS_PER_SQUARE = 64  # at least; raised until marker cells are whole texels


@dataclass(frozen=True)
class Texture:
    """``static``: hashable description; ``raster``: float32 data (a 1x1 dummy for analytic kinds)."""

    static: tuple
    raster: np.ndarray


def _charuco_raster(p: dict) -> np.ndarray:
    from lensfit.calibration.targets import charuco_board

    board = charuco_board(p["squares"], p["square_mm"], p["marker_mm"], p["dictionary"],
                          bool(p.get("legacy_pattern", False)))
    n = charuco_texels(p)
    img = board.generateImage((p["squares"][0] * n, p["squares"][1] * n), marginSize=0, borderBits=1)
    return np.where(img > 127, p["light"], p["dark"]).astype(np.float32)


def charuco_texels(p: dict) -> int:
    """Texels per square at which OpenCV draws the board exactly (whole-texel marker cells)."""
    from lensfit.calibration.targets import charuco_texels_per_square

    return charuco_texels_per_square(p["square_mm"], p["marker_mm"], p["dictionary"],
                                     minimum=CHARUCO_TEXELS_PER_SQUARE)


def _image_raster(p: dict) -> np.ndarray:
    import skimage.io

    img = skimage.io.imread(p["file"])
    if img.ndim == 3:
        img = img[..., :3].mean(axis=-1) if img.shape[-1] >= 3 else img[..., 0]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
    v = img.astype(np.float64) / scale
    if p["encoding"] == "srgb":
        from lensfit.io.images import srgb_to_linear

        v = srgb_to_linear(v)
    if (p.get("dark", 0.0), p.get("light", 1.0)) != (0.0, 1.0):
        v = p["dark"] + (p["light"] - p["dark"]) * v
    return v.astype(np.float32)


@functools.lru_cache(maxsize=64)
def _texture_cached(kind: str, size_mm: tuple[float, float], frozen_params: tuple) -> Texture:
    p = dict(frozen_params)
    w, h = size_mm
    dummy = np.zeros((1, 1), np.float32)
    if kind == "charuco":
        pw, ph = p["squares"][0] * p["square_mm"], p["squares"][1] * p["square_mm"]
        return Texture(("raster-nearest", w, h, pw, ph, float(p["light"])), _charuco_raster(p))
    if kind == "checkerboard":
        return Texture(("checkerboard", w, h, tuple(p["squares"]), p["square_mm"], float(p["dark"]), float(p["light"])),
                       dummy)
    if kind == "slanted-edge":
        return Texture(("slanted-edge", w, h, p["angle_deg"], p["edge_mm"], float(p["dark"]), float(p["light"])), dummy)
    if kind == "siemens-star":
        return Texture(("siemens-star", w, h, p["spokes"], float(p["dark"]), float(p["light"])), dummy)
    if kind == "image":
        return Texture(("raster-bilinear", w, h), _image_raster(p))
    if kind == "uniform":
        return Texture(("uniform", w, h, float(p["value"])), dummy)
    raise ValueError(f"unknown target kind {kind!r}")  # the scene schema makes this unreachable


def texture(target: TargetSpec) -> Texture:
    """The texture of a target (cached: a ChArUco raster is generated once per process).

    The cache key is everything that sets the appearance (kind, size and every parameter), not
    the TargetSpec's identity: two targets with one id but different values are different.
    """
    params = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in target.params.items()))
    return _texture_cached(target.target, tuple(target.size_mm), params)


def inside(static: tuple, x, y):
    """Whether target-plane points lie on the target (its ``size_mm`` rectangle)."""
    w, h = static[1], static[2]
    return (jnp.abs(x) <= 0.5 * w) & (jnp.abs(y) <= 0.5 * h)


def evaluate(static: tuple, raster, x, y):
    """Reflectance at target-plane points (x, y) in mm (JAX; traceable; float32)."""
    kind = static[0]
    if kind == "uniform":
        return jnp.full(jnp.shape(x), static[3], jnp.float32)
    if kind == "checkerboard":
        _, w, h, (nx, ny), sq, dark, light = static
        i = jnp.floor((x + 0.5 * nx * sq) / sq)
        j = jnp.floor((y + 0.5 * ny * sq) / sq)
        on_pattern = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        is_dark = on_pattern & (jnp.mod(i + j, 2.0) == 0.0)  # top-left square dark
        return jnp.where(is_dark, dark, light).astype(jnp.float32)
    if kind == "slanted-edge":
        _, w, h, angle, edge, dark, light = static
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        xr, yr = c * x + s * y, -s * x + c * y  # rotate by -angle into the square's frame
        is_dark = (jnp.abs(xr) <= 0.5 * edge) & (jnp.abs(yr) <= 0.5 * edge)
        return jnp.where(is_dark, dark, light).astype(jnp.float32)
    if kind == "siemens-star":
        _, w, h, spokes, dark, light = static
        r = jnp.hypot(x, y)
        phase = jnp.mod(jnp.arctan2(y, x) * (spokes / (2.0 * math.pi)), 1.0)
        is_dark = (r <= 0.5 * min(w, h)) & (phase < 0.5)
        return jnp.where(is_dark, dark, light).astype(jnp.float32)
    if kind == "raster-nearest":
        _, w, h, pw, ph, margin = static
        rows, cols = raster.shape
        ci = jnp.floor((x + 0.5 * pw) * (cols / pw))
        ri = jnp.floor((y + 0.5 * ph) * (rows / ph))
        on_pattern = (ci >= 0) & (ci < cols) & (ri >= 0) & (ri < rows)
        flat = (jnp.clip(ri, 0, rows - 1) * cols + jnp.clip(ci, 0, cols - 1)).astype(jnp.int32)
        return jnp.where(on_pattern, jnp.take(raster.reshape(-1), flat), jnp.float32(margin))
    if kind == "raster-bilinear":
        _, w, h = static
        rows, cols = raster.shape
        fx = jnp.clip((x + 0.5 * w) * (cols / w) - 0.5, 0.0, cols - 1.0)
        fy = jnp.clip((y + 0.5 * h) * (rows / h) - 0.5, 0.0, rows - 1.0)
        x0, y0 = jnp.floor(fx), jnp.floor(fy)
        ax, ay = fx - x0, fy - y0
        x0i, y0i = x0.astype(jnp.int32), y0.astype(jnp.int32)
        x1i, y1i = jnp.minimum(x0i + 1, cols - 1), jnp.minimum(y0i + 1, rows - 1)
        flat = raster.reshape(-1)

        def at(r, c):
            return jnp.take(flat, r * cols + c)

        top = at(y0i, x0i) * (1 - ax) + at(y0i, x1i) * ax
        bottom = at(y1i, x0i) * (1 - ax) + at(y1i, x1i) * ax
        return (top * (1 - ay) + bottom * ay).astype(jnp.float32)
    raise ValueError(f"unknown texture kind {kind!r}")


# --------------------------------------------------------------------------- straight edges (truth)


def edges(target: TargetSpec) -> list[dict]:
    """Straight dark/light edges of a target as segments in target-plane mm.

    Boards: every square side between cells of different colour (including the pattern's
    outer border against the light margin), merged into maximal straight runs would lose the
    per-square granularity estimators use, so each square side is one segment. Slanted edge:
    the four sides of the dark square. Other kinds have no straight edges.

    Returns
    -------
    list of dict with ``id`` (str), ``start_mm`` and ``end_mm`` ([x, y] in the target frame).
    """
    p, kind = target.params, target.target
    out: list[dict] = []
    if kind in ("charuco", "checkerboard"):
        nx, ny = p["squares"]
        sq = p["square_mm"]
        x0, y0 = -0.5 * nx * sq, -0.5 * ny * sq
        if kind == "charuco":
            raster = texture(target).raster
            n = charuco_texels(p)
            # A square's own colour is what its corner region shows (markers sit in the middle).
            dark = raster[n // 16::n, n // 16::n][:ny, :nx] < 0.5 * (p["dark"] + p["light"])
        else:
            dark = (np.add.outer(np.arange(ny), np.arange(nx)) % 2) == 0

        def is_dark(j, i):
            return bool(dark[j, i]) if 0 <= i < nx and 0 <= j < ny else False

        for j in range(ny + 1):  # horizontal sides: between row j-1 and row j
            for i in range(nx):
                if is_dark(j - 1, i) != is_dark(j, i):
                    out.append({"id": f"h{j}_{i}", "start_mm": [x0 + i * sq, y0 + j * sq],
                                "end_mm": [x0 + (i + 1) * sq, y0 + j * sq]})
        for i in range(nx + 1):  # vertical sides: between column i-1 and column i
            for j in range(ny):
                if is_dark(j, i - 1) != is_dark(j, i):
                    out.append({"id": f"v{i}_{j}", "start_mm": [x0 + i * sq, y0 + j * sq],
                                "end_mm": [x0 + i * sq, y0 + (j + 1) * sq]})
    elif kind == "slanted-edge":
        e, a = p["edge_mm"], math.radians(p["angle_deg"])
        c, s = math.cos(a), math.sin(a)
        corners = [(-e / 2, -e / 2), (e / 2, -e / 2), (e / 2, e / 2), (-e / 2, e / 2)]
        rot = [[c * x - s * y, s * x + c * y] for x, y in corners]
        for k, name in enumerate(("top", "right", "bottom", "left")):
            out.append({"id": name, "start_mm": rot[k], "end_mm": rot[(k + 1) % 4]})
    return out
