"""Writing a rendered stack folder, all or nothing.

Layout of DIR::

    stack.toml              what a photographer knows (read by lensfit)
    truth.json              the ground truth (never read by the fit)
    shot_000.png ...        16-bit linear PNG (or 16-bit TIFF, or float32 TIFF; raw sensor DN with
                            black/white levels under the exposure effect; DNG under mosaic)
    truth/shot_000_maps.npz per-pixel depth_mm and coc_diameter_px (float32; depth inf = background)

Everything is written into a temporary sibling folder first and renamed into place at the
end, so an interrupted render never leaves a half-written stack. An existing non-empty DIR is
replaced only with ``force=True``.
"""

from __future__ import annotations

import json
import os
import zipfile
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np

from synth.rendering import RenderResult, quantise_16bit


def _write_image(path: Path, image: np.ndarray, image_format: str) -> None:
    """Float radiance is quantised to 16 bits (or kept as float32); uint16 (raw DN) is written as is.
    (H, W, 3) images are RGB."""
    data = image if image.dtype == np.uint16 else (
        image.astype(np.float32) if image_format == "float-tiff" else quantise_16bit(image))
    if image_format == "png":
        import cv2

        if not cv2.imwrite(str(path), data[..., ::-1] if data.ndim == 3 else data):  # OpenCV writes BGR
            raise OSError(f"could not write {path}")
    else:
        import tifffile

        tifffile.imwrite(path, data, photometric="rgb" if data.ndim == 3 else "minisblack")


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _write_jpeg(path: Path, image: np.ndarray, raw: np.ndarray | None, levels: dict | None, exif: dict,
                quality: int) -> None:
    """An 8-bit sRGB JPEG with the camera record as EXIF, as a camera's JPEG (without its
    sharpening, noise reduction or tone curve). Sensor DN (exposure effect) are scaled by their
    black and white levels first."""
    from PIL import Image

    from synth.exif import pillow_exif

    if raw is not None and levels is not None:
        image = (raw.astype(np.float64) - levels["black_level"]) / (levels["white_level"] - levels["black_level"])
    data = np.round(255.0 * linear_to_srgb(np.asarray(image, np.float64))).astype(np.uint8)
    Image.fromarray(data, mode="RGB" if data.ndim == 3 else "L").save(
        path, "JPEG", quality=int(quality), exif=pillow_exif(exif))


def manifest_toml(manifest: dict) -> str:
    """stack.toml text: [camera], then one [[target]] and one [[image]] table per entry."""
    import tomli_w

    text = "# Written by synth: what a photographer knows about this stack (never the answer).\n\n"
    text += "[camera]\n" + tomli_w.dumps(manifest["camera"])
    if "lens" in manifest:
        text += "\n[lens]\n" + tomli_w.dumps(manifest["lens"])
    for section in ("target", "image"):
        for entry in manifest.get(section, []):
            text += f"\n[[{section}]]\n" + tomli_w.dumps(entry)
    return text


def check_out_dir(out: str | Path, force: bool) -> Path:
    """Refuse, before any work, a file, a folder holding anything synth did not write, or (without
    ``force``) a non-empty stack folder (``lensfit.outputs.writers.check_output``)."""
    from lensfit.outputs.writers import check_output

    return check_output(out, "--out", force=force, folder=True)


def _write_maps(path: Path, maps: dict[str, np.ndarray]) -> None:
    """``np.savez_compressed``'s file (an .npz that ``np.load`` reads), deflated at level 1: 3 %
    larger than its default level, at two thirds of the time (the maps of the demo's 12 shots:
    0.55 s at the default)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for key, array in maps.items():
            with archive.open(key + ".npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)


def _run_all(jobs: list) -> None:
    """Run the file writes on a few threads (OpenCV's PNG encoder and zlib's deflate release the
    GIL: the demo's 12 images and maps 0.33 -> 0.18 s, the same bytes). The first failure (or a
    stop) cancels the writes not yet begun and is raised once those under way have ended, so that
    the caller can discard its temporary folder with nothing still writing into it."""
    pool = ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1))
    futures = []
    try:
        futures = [pool.submit(job) for job in jobs]
        for future in futures:
            future.result()
    except BaseException:  # a failure or a stop: no write may still be running when the folder goes
        for future in futures:
            future.cancel()
        raise
    finally:
        pool.shutdown(wait=True)


def write_stack(result: RenderResult, out: str | Path, *, force: bool = False) -> Path:
    """Write a stack folder atomically; returns its path.

    The folder is written as a temporary sibling and renamed into place. An existing folder is
    replaced only with ``force`` and only when it holds nothing but a stack synth wrote (checked
    again just before the swap); its old contents are removed only then.

    Examples
    --------
    >>> import synth
    >>> synth.write_stack(synth.render("data_specs/scenes/demo.toml"), "out/demo", force=True)  # doctest: +SKIP
    PosixPath('out/demo')
    """
    from lensfit.outputs.writers import write_folder

    image_format = result.image_format

    def fill(tmp: Path) -> None:
        jobs = []  # the PNG/TIFF images and the truth maps: written by a few threads at once
        for name, image in result.images.items():
            if image_format == "dng":
                from synth.effects.mosaic import write_dng

                write_dng(tmp / name, result.raw[name], result.truth["effect_parameters"]["mosaic"]["pattern"],
                          result.levels[name]["black_level"], result.levels[name]["white_level"], result.exif[name])
            elif image_format == "jpeg":
                _write_jpeg(tmp / name, image, result.raw.get(name), result.levels.get(name), result.exif[name],
                            result.jpeg_quality)
            else:
                jobs.append(partial(_write_image, tmp / name, result.raw.get(name, image), image_format))
        (tmp / "truth").mkdir()
        jobs.extend(partial(_write_maps, tmp / name, maps) for name, maps in result.maps.items())
        _run_all(jobs)
        truth = dict(result.truth)
        truth["image_format"] = {"png": "16-bit linear PNG", "tiff": "16-bit linear TIFF",
                                 "float-tiff": "float32 linear TIFF", "dng": "DNG (Bayer CFA, raw DN)",
                                 "jpeg": f"8-bit sRGB JPEG, quality {result.jpeg_quality}"}[image_format]
        if result.raw and image_format not in ("dng", "jpeg"):
            truth["image_format"] += "; sensor DN with the black and white levels in stack.toml"
        (tmp / "truth.json").write_text(json.dumps(truth, indent=1, allow_nan=False))
        (tmp / "stack.toml").write_text(manifest_toml(result.manifest))

    return write_folder(out, fill, force=force)
