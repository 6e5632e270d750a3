"""A contact sheet of a render: every shot, small, in sRGB, for people to look at.

Stack files hold linear values (they look dark and flat in an image viewer) or raw DNG; the
sheet shows what each file records (``recorded``: the rendered radiance, or the sensor's DN
linearised with its black and white levels, a Bayer mosaic shown by 2 x 2 super-pixels),
downscaled by averaging in linear light, with one exposure for all shots (the 99.5th percentile of all pixels maps to white, so
shots stay comparable), encoded with the sRGB transfer curve (IEC 61966-2-1), and labelled
with the shot name.
"""

from __future__ import annotations

import math

import numpy as np


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values in [0, 1]."""
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def _downscale(img: np.ndarray, k: int) -> np.ndarray:
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    img = img[:h, :w]
    return img.reshape(h // k, k, w // k, k, *img.shape[2:]).mean(axis=(1, 3))


def contact_sheet(images: dict[str, np.ndarray], *, max_tile_px: int = 400, gap_px: int = 4) -> np.ndarray:
    """RGB uint8 sheet of the images (name -> linear (H, W) or (H, W, 3)), in a near-square grid."""
    import cv2

    names = list(images)
    first = images[names[0]]
    k = max(1, math.ceil(max(first.shape[:2]) / max_tile_px))
    tiles = []
    for name in names:
        img = np.asarray(images[name], np.float64)
        img = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=-1)
        tiles.append(_downscale(img, k))
    white = float(np.percentile(np.concatenate([t.ravel() for t in tiles]), 99.5)) or 1.0
    th, tw = tiles[0].shape[:2]
    cols = math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / cols)
    sheet = np.zeros((rows * th + (rows + 1) * gap_px, cols * tw + (cols + 1) * gap_px, 3), np.uint8)
    for i, (name, tile) in enumerate(zip(names, tiles)):
        r, c = divmod(i, cols)
        y, x = gap_px + r * (th + gap_px), gap_px + c * (tw + gap_px)
        enc = np.round(255 * linear_to_srgb(tile / white)).astype(np.uint8)
        label = name.rsplit(".", 1)[0]
        cv2.putText(enc, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(enc, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        sheet[y:y + th, x:x + tw] = enc
    return sheet


def recorded(result) -> dict[str, np.ndarray]:
    """Per image of a ``synth.rendering.RenderResult``, the linear values its file records."""
    out = {}
    for name, img in result.images.items():
        raw = result.raw.get(name)
        if raw is None:
            out[name] = img
            continue
        lv = result.levels[name]
        lin = (raw.astype(np.float64) - lv["black_level"]) / (lv["white_level"] - lv["black_level"])
        mosaic = result.truth.get("effect_parameters", {}).get("mosaic")
        if mosaic is not None:
            lin = _superpixels(lin, mosaic["pattern"])
        out[name] = lin
    return out


def _superpixels(cfa: np.ndarray, pattern: str) -> np.ndarray:
    """A Bayer frame as RGB, each 2 x 2 cell one colour (its R, mean G, B), at full size."""
    h, w = (cfa.shape[0] // 2) * 2, (cfa.shape[1] // 2) * 2
    cells = cfa[:h, :w].reshape(h // 2, 2, w // 2, 2)
    sites = {(0, 0): pattern[0], (0, 1): pattern[1], (1, 0): pattern[2], (1, 1): pattern[3]}
    rgb = np.zeros((h // 2, w // 2, 3))
    count = np.zeros(3)
    for (i, j), colour in sites.items():
        c = "RGB".index(colour)
        rgb[..., c] += cells[:, i, :, j]
        count[c] += 1
    return np.repeat(np.repeat(rgb / count, 2, axis=0), 2, axis=1)


def write_preview(path, images: dict[str, np.ndarray], *, force: bool = True, **kwargs) -> None:
    """Write the contact sheet as PNG (a temporary sibling, then renamed), tagged ``Software =
    synth VERSION`` so that ``--force`` may replace it later (``lensfit.outputs.writers.written_by``)."""
    from pathlib import Path

    from PIL import Image, PngImagePlugin

    from lensfit.outputs.writers import software_tag, write_all

    sheet = contact_sheet(images, **kwargs)
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", software_tag("synth"))
    write_all([(Path(path), lambda tmp: Image.fromarray(sheet).save(tmp, format="PNG", pnginfo=info))], force=force)
