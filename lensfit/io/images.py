"""Reading one image file: PNG, TIFF, JPEG, DNG and camera RAW, as linear float64 grey.

Every decoder takes the file's bytes where the caller has them (:func:`read_inside`: read from a
descriptor whose real path was checked to lie inside the stack folder, so that a link swapped in
after the check is not followed) and checks the size its header declares against the pixel
budget before decoding the pixels.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lensfit.errors import SpecError

RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw", ".nrw",
                ".3fr", ".iiq", ".erf", ".kdc", ".mrw", ".x3f"}
RASTER_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg"}
#: JPEG files: 8-bit, sRGB-encoded unless the manifest says otherwise.
JPEG_SUFFIXES = {".jpg", ".jpeg"}


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding to linear light (values in [0, 1])."""
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _to_grey(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[-1] in (3, 4):
        return img[..., 0] * 0.2126 + img[..., 1] * 0.7152 + img[..., 2] * 0.0722
    if img.ndim == 3 and img.shape[-1] in (1, 2):
        return img[..., 0]
    raise ValueError(f"unsupported image shape {img.shape}")


def _source(path: Path, data: bytes | None):
    """What a decoder opens: the file's bytes where given, else its path."""
    return path if data is None else io.BytesIO(data)


#: Bytes per pixel an image file may hold at most (uncompressed 32-bit float RGBA), over the pixel
#: budget: a larger file is refused before it is read (a sparse file of 4 GB is small on disk).
FILE_BYTES_PER_PX = 16
FILE_OVERHEAD_BYTES = 16 << 20


def read_inside(path: Path, folder: Path, max_pixels: int | None = None) -> bytes:
    """The bytes of ``path``, refused unless the file opened lies inside ``folder``: checked on the
    open descriptor (its real path, or its device and inode against the resolved path's), so that
    a link swapped in between a check of the name and the read is not followed out of the folder.
    A file larger than any image of ``max_pixels`` pixels (default: ``lensfit.io.limits``) is refused
    unread."""
    from lensfit.io.limits import DEFAULT_MAX_MEGAPIXELS

    budget = (max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6)) * FILE_BYTES_PER_PX + FILE_OVERHEAD_BYTES
    inside = folder.resolve()
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        raise SpecError(path, "", "file not found") from None
    with os.fdopen(fd, "rb") as fh:
        proc = Path(f"/proc/self/fd/{fd}")
        if proc.is_symlink():
            real = Path(os.readlink(proc))
        else:  # no /proc: the descriptor must be the very file the resolved name inside is
            real = path.resolve()
            st, named = os.fstat(fd), os.stat(real)
            if (st.st_dev, st.st_ino) != (named.st_dev, named.st_ino):
                real = Path("/")
        if not real.is_relative_to(inside):
            raise SpecError(path, "", f"leads outside the stack folder {folder} (to {real}); copy the image into "
                            "the folder (or pass --allow-outside-stack)")
        size = os.fstat(fd).st_size
        if size > budget:
            raise SpecError(path, "", f"holds {size / 1e9:.1f} GB, more than any image within the pixel budget "
                            "(--max-megapixels) needs; is it an image?")
        return fh.read()


def _png_header(path: Path, data: bytes | None = None) -> tuple[int, int]:
    """(height, width) from a PNG's IHDR chunk (the first 24 bytes), without decoding."""
    if data is not None:
        head = data[:24]
    else:
        with path.open("rb") as fh:
            head = fh.read(24)
    if len(head) < 24 or not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        raise SpecError(path, "", "is not a PNG file (bad signature or header); is it truncated or misnamed?")
    return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")


def image_size(path: str | Path, data: bytes | None = None) -> tuple[int, int]:
    """(height, width) of an image from its header (``data``: the file's bytes, where read), without
    decoding the pixels.

    RAW/DNG: the size LibRaw's postprocess produces (no rotation); PNG: IHDR; TIFF: the first page.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in RAW_SUFFIXES:
            import rawpy

            raw = rawpy.RawPy()
            try:
                raw.open_file(str(path)) if data is None else raw.open_buffer(io.BytesIO(data))
                sizes = raw.sizes
                return int(sizes.height), int(sizes.width)
            finally:
                raw.close()
        if suffix == ".png":
            return _png_header(path, data)
        if suffix in JPEG_SUFFIXES:
            from PIL import Image

            with Image.open(_source(path, data)) as im:  # reads the header only
                if im.format != "JPEG":
                    raise SpecError(path, "", f"is not a JPEG file (it holds {im.format}); is it misnamed?")
                return int(im.size[1]), int(im.size[0])
        if suffix in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(_source(path, data)) as tif:
                page = tif.pages[0]
                return int(page.imagelength), int(page.imagewidth)
    except FileNotFoundError:
        raise SpecError(path, "", "file not found") from None
    except SpecError:
        raise
    except Exception as exc:  # decoders raise many types for corrupt or truncated headers
        raise SpecError(path, "", f"cannot be read ({type(exc).__name__}: {exc})") from None
    raise _unsupported(path, suffix)


def _unsupported(path: Path, suffix: str) -> SpecError:
    return SpecError(path, "", f"unsupported file type {suffix!r}; use PNG, TIFF, JPEG, DNG or a camera RAW file")


def _decode_jpeg(path: Path, data: bytes | None = None) -> np.ndarray:
    """An 8-bit JPEG (grey or colour) as stored (its size was checked from the header)."""
    from PIL import Image

    with Image.open(_source(path, data)) as im:
        im.load()
        if im.mode not in ("L", "RGB"):
            im = im.convert("RGB")
        return np.asarray(im)


def _check_png_chunks(path: Path, data: np.ndarray) -> None:
    """Refuse a PNG whose chunks claim more bytes than the file holds: the decoder allocates by the
    claimed length (a 12 KB file claiming 2 GB took 2.1 GB before failing)."""
    raw = data.tobytes()
    at = 8  # after the signature
    while at + 8 <= len(raw):
        length = int.from_bytes(raw[at:at + 4], "big")
        kind = raw[at + 4:at + 8]
        if length > len(raw) - at - 12:
            raise SpecError(path, "", f"is not a whole PNG: its {kind.decode('latin-1')!r} chunk claims {length} bytes, "
                            f"{len(raw) - at - 12} remain in the file; is it truncated or corrupt?")
        if kind == b"IEND":
            return
        at += 12 + length


_QUIET_LOCK = threading.Lock()
_QUIET = {"users": 0, "level": None}


@contextlib.contextmanager
def _opencv_quiet():
    """OpenCV's log silenced while any thread decodes (the level is process-wide: saved by the
    first thread in, restored by the last one out)."""
    import cv2

    log = cv2.utils.logging
    with _QUIET_LOCK:
        if _QUIET["users"] == 0:
            _QUIET["level"] = log.getLogLevel()
            log.setLogLevel(log.LOG_LEVEL_SILENT)
        _QUIET["users"] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _QUIET["users"] -= 1
            if _QUIET["users"] == 0:
                log.setLogLevel(_QUIET["level"])


def _decode_png(path: Path, data: bytes | None = None) -> np.ndarray:
    """Every PNG layout at its full bit depth (1-16 bit grey, grey + alpha, RGB, RGBA, palette)."""
    import cv2

    buffer = np.fromfile(path, dtype=np.uint8) if data is None else np.frombuffer(data, np.uint8)
    _check_png_chunks(path, buffer)
    with _opencv_quiet():  # a corrupt file is reported below as one line, not as OpenCV's log
        img = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SpecError(path, "", "cannot be decoded as PNG; is it truncated or corrupt?")
    if img.ndim == 3 and img.shape[-1] >= 3:  # OpenCV orders colour channels BGR(A)
        img = img[..., [2, 1, 0, *range(3, img.shape[-1])]]
    return img


def _decode_tiff(path: Path, data: bytes | None = None) -> np.ndarray:
    """The first page of a TIFF, samples on the last axis (planar or interleaved)."""
    import tifffile

    with tifffile.TiffFile(_source(path, data)) as tif:
        page = tif.pages[0]
        img = page.asarray()
        axes = page.axes
    if "S" in axes and img.ndim == len(axes):
        img = np.moveaxis(img, axes.index("S"), -1)
    return img


def integers_to_linear(img: np.ndarray, black_level: float | None = None,
                       white_level: float | None = None) -> np.ndarray:
    """An integer raster in full-scale units, float64: over its type's maximum, or from
    ``black_level`` to ``white_level`` (:func:`read_raster`)."""
    if black_level is not None or white_level is not None:
        black = float(black_level or 0.0)
        white = float(white_level if white_level is not None else np.iinfo(img.dtype).max)
        return (img.astype(np.float64) - black) / (white - black)
    return np.divide(img, float(np.iinfo(img.dtype).max), dtype=np.float64)  # (one pass, no copy)


@dataclass(frozen=True)
class HeldRaster:
    """A single-channel integer image as its file holds it (2 bytes a pixel for 16-bit, 1 for
    8-bit, against 8 as float64), with what turns it into the linear image :func:`read_image`
    returns: the same values, a fraction of a decode's time (:meth:`linear`)."""

    values: np.ndarray
    black_level: float | None = None
    white_level: float | None = None
    encoding: str = "linear"

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes)

    def rotated(self, quarter_turns: int) -> "HeldRaster":
        return dataclasses.replace(self, values=np.ascontiguousarray(np.rot90(self.values, quarter_turns)))

    def linear(self) -> np.ndarray:
        img = integers_to_linear(self.values, self.black_level, self.white_level)
        return srgb_to_linear(np.clip(img, 0.0, 1.0)) if self.encoding == "srgb" else img


def read_raster(path: Path, black_level: float | None = None, white_level: float | None = None, *,
                max_pixels: int | None = None, data: bytes | None = None,
                keep_integers: bool = False) -> np.ndarray | HeldRaster:
    """PNG/TIFF -> float64 in full-scale units (integers / max of their type; floats as stored).

    Every channel layout is read at its full bit depth (16-bit colour PNGs included). The size is
    checked from the header against ``max_pixels`` (default: ``lensfit.io.limits``) before decoding.
    With ``black_level``/``white_level`` (raw sensor values stored in an integer file, e.g.
    12-bit DN in a 16-bit PNG) integers map to ``(value - black) / (white - black)`` instead.
    ``keep_integers``: a single-channel integer image comes back as its integers
    (:class:`HeldRaster`), to be held compactly and made linear when used.
    """
    from lensfit.io.limits import DEFAULT_MAX_MEGAPIXELS, check_image_size

    check_image_size(path, *image_size(path, data), max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6))
    try:
        suffix = path.suffix.lower()
        img = (_decode_tiff(path, data) if suffix in (".tif", ".tiff") else
               _decode_jpeg(path, data) if suffix in JPEG_SUFFIXES else _decode_png(path, data))
    except FileNotFoundError:
        raise SpecError(path, "", "file not found") from None
    except SpecError:
        raise
    except MemoryError:
        raise SpecError(path, "", "does not fit in memory while decoding; lower --max-megapixels or use a "
                        "machine with more memory") from None
    except Exception as exc:  # decoders raise many types for corrupt or truncated files
        raise SpecError(path, "", f"cannot be decoded ({type(exc).__name__}: {exc}); is it truncated?") from None
    img = np.asarray(img)
    if img.dtype == np.bool_:
        img = img.astype(np.uint8)
    if img.dtype.kind in "ui":
        if keep_integers and img.ndim == 2:
            return HeldRaster(img, black_level, white_level)
        out = integers_to_linear(img, black_level, white_level)
    elif img.dtype.kind == "f":
        out = img.astype(np.float64)
        if np.isnan(out).any():
            raise SpecError(path, "", f"float image holds {int(np.isnan(out).sum())} NaN pixels; "
                            "write finite values (e.g. 0 for missing data)")
        if np.isinf(out).any():
            raise SpecError(path, "", "float image holds infinite values")
        if out.size and float(out.max()) <= 0.0:  # (noise after a black level dips below 0; light is above it)
            raise SpecError(path, "", f"float image holds no positive value (from {float(out.min()):.4g} to "
                            f"{float(out.max()):.4g}): no light was recorded; is it a difference image, or were its "
                            "values negated? write linear light, 0 for black")
    else:
        raise SpecError(path, "", f"unsupported pixel type {img.dtype}")
    try:
        return _to_grey(out)
    except ValueError as exc:
        raise SpecError(path, "", str(exc)) from None


def read_raw(path: Path, *, max_pixels: int | None = None, data: bytes | None = None) -> np.ndarray:
    """DNG or camera RAW -> linear float64 grey, full scale 1 (rawpy, gamma 1, no auto-brightening).

    The size is checked from the header against ``max_pixels`` before decoding."""
    import rawpy

    from lensfit.io.limits import DEFAULT_MAX_MEGAPIXELS, check_image_size

    check_image_size(path, *image_size(path, data), max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6))
    try:
        with rawpy.imread(str(path) if data is None else io.BytesIO(data)) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, user_flip=0,
                                  use_camera_wb=True, output_color=rawpy.ColorSpace.raw,
                                  demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD, adjust_maximum_thr=0.0)
    except FileNotFoundError:
        raise SpecError(path, "", "file not found") from None
    except Exception as exc:  # rawpy opens corrupt files and fails only when decoding
        raise SpecError(path, "", f"cannot be decoded as RAW ({type(exc).__name__}: {exc})") from None
    return _to_grey(rgb.astype(np.float64) / 65535.0)


def read_image(path: str | Path, encoding: str = "linear", *, black_level: float | None = None,
               white_level: float | None = None, max_pixels: int | None = None,
               data: bytes | None = None, keep_integers: bool = False) -> np.ndarray | HeldRaster:
    """Read one image as linear float64 grey intensity (H, W), full scale 1.

    ``black_level``/``white_level``: raw integer levels of a PNG/TIFF (see ``read_raster``);
    RAW and DNG files carry their own. ``max_pixels``: the pixel budget, checked from the header
    before decoding (default ``lensfit.io.limits.DEFAULT_MAX_MEGAPIXELS``). ``data``: the file's
    bytes, where read already (:func:`read_inside`); ``path`` then names it and gives its type.
    ``keep_integers``: a single-channel integer PNG/TIFF comes back as a :class:`HeldRaster`
    (its :meth:`HeldRaster.linear` is what this function returns otherwise).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in RAW_SUFFIXES:
        return read_raw(path, max_pixels=max_pixels, data=data)
    if suffix not in RASTER_SUFFIXES:
        raise _unsupported(path, suffix)
    img = read_raster(path, black_level, white_level, max_pixels=max_pixels, data=data, keep_integers=keep_integers)
    if isinstance(img, HeldRaster):
        return dataclasses.replace(img, encoding=encoding)
    return srgb_to_linear(np.clip(img, 0.0, 1.0)) if encoding == "srgb" else img
