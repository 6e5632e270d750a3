"""Reading an image stack: ``stack.toml`` and its images, as linear float64 intensities.

Formats: PNG and TIFF (8/16-bit integer or float), JPEG (8-bit), DNG and camera RAW (through
rawpy, decoded linearly: no gamma, no auto-brightening, 16-bit, no rotation). Colour images are
reduced to luminance-weighted grey (Rec. 709 weights) in linear light. sRGB-encoded images are
linearised when the manifest says ``encoding = "srgb"``, which is the default for JPEG (a
camera's JPEG is sRGB-encoded; its in-camera sharpening, noise reduction and tone curve still
bias blur measurement: prefer RAW where the camera writes it).

Every refusal is a :class:`lensfit.errors.SpecError` naming the file (and the manifest field
where one is involved): unreadable or truncated files, images of inconsistent size, NaN in
float images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.errors import SpecError
from lensfit.specs import load_toml, validate

RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw", ".nrw",
                ".3fr", ".iiq", ".erf", ".kdc", ".mrw", ".x3f"}
RASTER_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg"}
#: JPEG files: 8-bit, sRGB-encoded unless the manifest says otherwise.
JPEG_SUFFIXES = {".jpg", ".jpeg"}


@dataclass(frozen=True)
class ImageEntry:
    """One image of a stack as the manifest describes it."""

    index: int
    file: Path
    encoding: str
    setting: str
    distance_mm: float | None = None
    black_level: float | None = None  # raw integer levels (sensor DN in a PNG/TIFF)
    white_level: float | None = None
    targets: tuple[str, ...] | None = None  # ids of the targets it shows (None: any)
    #: counter-clockwise turn (degrees) that brings the pixels back to the sensor's orientation
    rotate_deg: int = 0


@dataclass
class Stack:
    """A stack folder: manifest fields and image entries; images are read on demand.

    Attributes
    ----------
    path : the folder
    pixel_pitch_mm : from ``camera.pixel_pitch_mm``, or ``sensor_width_mm`` / image width
    targets : the ``[[target]]`` tables as dicts
    images : image entries in manifest order
    shape : (height, width) shared by every image
    """

    path: Path
    manifest_path: Path
    pixel_pitch_mm: float
    targets: list[dict[str, Any]]
    images: list[ImageEntry]
    shape: tuple[int, int]
    camera: dict[str, Any] = field(default_factory=dict)
    intrinsics: dict[str, dict[str, Any]] = field(default_factory=dict)
    max_pixels: int | None = None
    #: what is known of the lens (``[lens]``: ``pupil_magnification``, a value or a (lo, hi) range;
    #: ``focusing``, unit, internal or unknown; ``ideal``, a lens without aberrations)
    lens: dict[str, Any] = field(default_factory=dict)
    #: images kept in memory once read (None: read again each time; :meth:`holding`)
    hold: dict[int, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def encoded(self) -> bool:
        """Whether any image is declared sRGB-encoded (``encoding = "srgb"``) rather than linear."""
        return any(im.encoding == "srgb" for im in self.images)

    @property
    def settings(self) -> list[str]:
        """Setting labels in first-seen order."""
        seen: dict[str, None] = {}
        for im in self.images:
            seen.setdefault(im.setting, None)
        return list(seen)

    def holding(self, limit_bytes: int) -> "Stack":
        """This stack keeping its images in memory once read (:attr:`hold`), where all of them fit
        in ``limit_bytes`` as float64; else (or where it holds them already) this stack itself."""
        if self.hold is not None or len(self.images) * self.shape[0] * self.shape[1] * 8 > limit_bytes:
            return self
        return replace(self, hold={})

    def read(self, index: int) -> np.ndarray:
        """Image ``index`` as linear float64 intensity (H, W), full scale 1 (where the stack holds
        its images, the one array read first: not to be modified)."""
        if self.hold is not None and index in self.hold:
            return self.hold[index]
        entry = self.images[index]
        image = read_image(entry.file, entry.encoding, black_level=entry.black_level, white_level=entry.white_level,
                           max_pixels=self.max_pixels)
        if entry.rotate_deg:
            image = np.ascontiguousarray(np.rot90(image, entry.rotate_deg // 90))
        if self.hold is not None:
            self.hold[index] = image
        return image


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


def _png_header(path: Path) -> tuple[int, int]:
    """(height, width) from a PNG's IHDR chunk (the first 24 bytes), without decoding."""
    with path.open("rb") as fh:
        head = fh.read(24)
    if len(head) < 24 or not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        raise SpecError(path, "", "is not a PNG file (bad signature or header); is it truncated or misnamed?")
    return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")


def image_size(path: str | Path) -> tuple[int, int]:
    """(height, width) of an image from its header, without decoding the pixels.

    RAW/DNG: the size LibRaw's postprocess produces (no rotation); PNG: IHDR; TIFF: the first page.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in RAW_SUFFIXES:
            import rawpy

            raw = rawpy.RawPy()
            try:
                raw.open_file(str(path))
                sizes = raw.sizes
                return int(sizes.height), int(sizes.width)
            finally:
                raw.close()
        if suffix == ".png":
            return _png_header(path)
        if suffix in JPEG_SUFFIXES:
            from PIL import Image

            with Image.open(path) as im:  # reads the header only
                if im.format != "JPEG":
                    raise SpecError(path, "", f"is not a JPEG file (it holds {im.format}); is it misnamed?")
                return int(im.size[1]), int(im.size[0])
        if suffix in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(path) as tif:
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


def _decode_jpeg(path: Path) -> np.ndarray:
    """An 8-bit JPEG (grey or colour) as stored (its size was checked from the header)."""
    from PIL import Image

    with Image.open(path) as im:
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


def _decode_png(path: Path) -> np.ndarray:
    """Every PNG layout at its full bit depth (1-16 bit grey, grey + alpha, RGB, RGBA, palette)."""
    import cv2

    data = np.fromfile(path, dtype=np.uint8)
    _check_png_chunks(path, data)
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)  # a corrupt file is reported below as one line, not as OpenCV's log
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    finally:
        log.setLogLevel(level)
    if img is None:
        raise SpecError(path, "", "cannot be decoded as PNG; is it truncated or corrupt?")
    if img.ndim == 3 and img.shape[-1] >= 3:  # OpenCV orders colour channels BGR(A)
        img = img[..., [2, 1, 0, *range(3, img.shape[-1])]]
    return img


def _decode_tiff(path: Path) -> np.ndarray:
    """The first page of a TIFF, samples on the last axis (planar or interleaved)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        img = page.asarray()
        axes = page.axes
    if "S" in axes and img.ndim == len(axes):
        img = np.moveaxis(img, axes.index("S"), -1)
    return img


def read_raster(path: Path, black_level: float | None = None, white_level: float | None = None, *,
                max_pixels: int | None = None) -> np.ndarray:
    """PNG/TIFF -> float64 in full-scale units (integers / max of their type; floats as stored).

    Every channel layout is read at its full bit depth (16-bit colour PNGs included). The size is
    checked from the header against ``max_pixels`` (default: ``lensfit.limits``) before decoding.
    With ``black_level``/``white_level`` (raw sensor values stored in an integer file, e.g.
    12-bit DN in a 16-bit PNG) integers map to ``(value - black) / (white - black)`` instead.
    """
    from lensfit.limits import DEFAULT_MAX_MEGAPIXELS, check_image_size

    check_image_size(path, *image_size(path), max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6))
    try:
        suffix = path.suffix.lower()
        img = (_decode_tiff(path) if suffix in (".tif", ".tiff") else
               _decode_jpeg(path) if suffix in JPEG_SUFFIXES else _decode_png(path))
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
        if black_level is not None or white_level is not None:
            black = float(black_level or 0.0)
            white = float(white_level if white_level is not None else np.iinfo(img.dtype).max)
            out = (img.astype(np.float64) - black) / (white - black)
        else:
            out = img.astype(np.float64) / float(np.iinfo(img.dtype).max)
    elif img.dtype.kind == "f":
        out = img.astype(np.float64)
        if np.isnan(out).any():
            raise SpecError(path, "", f"float image holds {int(np.isnan(out).sum())} NaN pixels; "
                            "write finite values (e.g. 0 for missing data)")
        if np.isinf(out).any():
            raise SpecError(path, "", "float image holds infinite values")
    else:
        raise SpecError(path, "", f"unsupported pixel type {img.dtype}")
    try:
        return _to_grey(out)
    except ValueError as exc:
        raise SpecError(path, "", str(exc)) from None


def read_raw(path: Path, *, max_pixels: int | None = None) -> np.ndarray:
    """DNG or camera RAW -> linear float64 grey, full scale 1 (rawpy, gamma 1, no auto-brightening).

    The size is checked from the header against ``max_pixels`` before decoding."""
    import rawpy

    from lensfit.limits import DEFAULT_MAX_MEGAPIXELS, check_image_size

    check_image_size(path, *image_size(path), max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6))
    try:
        with rawpy.imread(str(path)) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, user_flip=0,
                                  use_camera_wb=True, output_color=rawpy.ColorSpace.raw,
                                  demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD, adjust_maximum_thr=0.0)
    except FileNotFoundError:
        raise SpecError(path, "", "file not found") from None
    except Exception as exc:  # rawpy opens corrupt files and fails only when decoding
        raise SpecError(path, "", f"cannot be decoded as RAW ({type(exc).__name__}: {exc})") from None
    return _to_grey(rgb.astype(np.float64) / 65535.0)


def read_image(path: str | Path, encoding: str = "linear", *, black_level: float | None = None,
               white_level: float | None = None, max_pixels: int | None = None) -> np.ndarray:
    """Read one image as linear float64 grey intensity (H, W), full scale 1.

    ``black_level``/``white_level``: raw integer levels of a PNG/TIFF (see ``read_raster``);
    RAW and DNG files carry their own. ``max_pixels``: the pixel budget, checked from the header
    before decoding (default ``lensfit.limits.DEFAULT_MAX_MEGAPIXELS``).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in RAW_SUFFIXES:
        return read_raw(path, max_pixels=max_pixels)
    if suffix not in RASTER_SUFFIXES:
        raise _unsupported(path, suffix)
    img = read_raster(path, black_level, white_level, max_pixels=max_pixels)
    return srgb_to_linear(np.clip(img, 0.0, 1.0)) if encoding == "srgb" else img


#: Squares along one side of a board at most: printed boards have up to a few dozen; more is a
#: typing slip, and the detector's work and memory grow with the board's area.
MAX_SQUARES_PER_SIDE = 200
#: Images one stack lists at most (a day's brackets run to some hundreds).
MAX_IMAGES = 5000


def _check_board(manifest_path: Path, i: int, t: dict[str, Any]) -> None:
    """Refuse a board no detector can use: too many squares, a marker as large as its square, an
    ArUco dictionary OpenCV does not have or that holds too few markers for the board."""
    field = f"target[{i}]"
    squares = t.get("squares")
    if squares is not None and max(squares) > MAX_SQUARES_PER_SIDE:
        raise SpecError(manifest_path, f"{field}.squares", f"got {squares}: at most {MAX_SQUARES_PER_SIDE} squares "
                        "along a side; count the squares of the printed board")
    if t["kind"] != "charuco":
        return
    if not t["marker_mm"] < t["square_mm"]:
        raise SpecError(manifest_path, f"{field}.marker_mm", f"got {t['marker_mm']:g}: a marker lies inside its "
                        f"square, so it must be smaller than square_mm ({t['square_mm']:g}); measure both on the print")
    from lensfit.targets import aruco_dictionary, aruco_dictionary_names

    name = t["dictionary"]
    known = aruco_dictionary_names()
    if name not in known:
        raise SpecError(manifest_path, f"{field}.dictionary", f"got {name!r}: not an ArUco dictionary OpenCV knows; "
                        f"e.g. {', '.join(k for k in known if k.startswith('DICT_4X4') or k.startswith('DICT_5X5'))}")
    capacity = aruco_dictionary(name).bytesList.shape[0]
    if squares[0] * squares[1] // 2 > capacity:
        raise SpecError(manifest_path, f"{field}.squares", f"got {squares}: a ChArUco board of that size needs "
                        f"{squares[0] * squares[1] // 2} markers and {name} holds {capacity}; check the squares "
                        "and the dictionary printed on the board")


def load_stack(path: str | Path, *, max_pixels: int | None = None, allow_outside: bool = False) -> Stack:
    """Read and validate a stack folder (or its ``stack.toml``); images are checked for
    existence, the pixel budget and a common size (from their headers), and read later on demand.

    Parameters
    ----------
    path : the stack folder or its stack.toml
    max_pixels : refuse images declaring more pixels (default ``lensfit.limits.DEFAULT_MAX_MEGAPIXELS``)
    allow_outside : read image files outside the stack folder (``../``, absolute paths, symbolic
        links that lead out); refused by default, naming the entry
    """
    from lensfit.limits import DEFAULT_MAX_MEGAPIXELS, check_image_size

    max_pixels = max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6)
    path = Path(path)
    manifest_path = path / "stack.toml" if path.is_dir() else path
    folder = manifest_path.parent
    if not manifest_path.exists():
        raise SpecError(manifest_path, "", "no stack.toml here; a stack folder needs one (see "
                        "data_specs/schemas/stack.schema.json)")
    data = load_toml(manifest_path)
    validate(data, "stack", manifest_path)
    ids = [t["id"] for t in data.get("target", [])]
    for i, tid in enumerate(ids):
        if ids.index(tid) != i:
            raise SpecError(manifest_path, f"target[{i}].id", f"got {tid!r}: target ids must be unique")
    for i, t in enumerate(data.get("target", [])):
        need = {"charuco": ("squares", "square_mm", "marker_mm", "dictionary"),
                "checkerboard": ("squares", "square_mm"), "slanted-edge": ("edge_mm",)}[t["kind"]]
        for name in need:
            if name not in t:
                raise SpecError(manifest_path, f"target[{i}].{name}", f"is required for kind = {t['kind']!r}")
        _check_board(manifest_path, i, t)
    images = []
    shape = None
    inside = folder.resolve()
    first_of: dict[Path, int] = {}
    if len(data["image"]) > MAX_IMAGES:
        raise SpecError(manifest_path, "image", f"lists {len(data['image'])} images, more than {MAX_IMAGES}; a stack "
                        "of that many is split into stacks of one lens setting each")
    for i, entry in enumerate(data["image"]):
        file = folder / entry["file"]
        if file.resolve() in first_of:
            j = first_of[file.resolve()]
            raise SpecError(manifest_path, f"image[{i}].file", f"got {entry['file']!r}, the file image[{j}] lists "
                            "already; list each photo once (one photo has one setting)")
        first_of[file.resolve()] = i
        if not allow_outside and not file.resolve().is_relative_to(inside):
            raise SpecError(manifest_path, f"image[{i}].file", f"got {entry['file']!r}: it leads outside the stack "
                            f"folder {folder}; copy the image into the folder (or pass --allow-outside-stack)")
        if not file.is_file():
            raise SpecError(manifest_path, f"image[{i}].file", f"got {entry['file']!r}: no such file in {folder}")
        if entry.get("white_level", math.inf) <= entry.get("black_level", 0):
            raise SpecError(manifest_path, f"image[{i}].white_level", f"got {entry['white_level']}: must exceed "
                            f"black_level ({entry.get('black_level', 0)})")
        for j, tid in enumerate(entry.get("targets", [])):
            if tid not in ids:
                raise SpecError(manifest_path, f"image[{i}].targets[{j}]", f"got {tid!r}: no [[target]] has this id; "
                                f"valid: {', '.join(ids)}")
        size = image_size(file)
        check_image_size(file, *size, max_pixels)
        turned = entry.get("rotate_deg", 0) in (90, 270)
        if turned:
            size = (size[1], size[0])
        if shape is None:
            shape = size
        elif size != shape:
            hint = ("; a portrait photo whose pixels were turned takes rotate_deg = 90 or 270 in its [[image]]"
                    if size == (shape[1], shape[0]) else "")
            raise SpecError(file, "", f"is {size[1]} x {size[0]} px{' (after its rotate_deg)' if turned else ''} but "
                            f"{images[0].file.name} is "
                            f"{shape[1]} x {shape[0]}; every image of a stack must have the same size{hint}")
        default_encoding = "srgb" if file.suffix.lower() in JPEG_SUFFIXES else "linear"
        images.append(ImageEntry(index=i, file=file, encoding=entry.get("encoding", default_encoding),
                                 setting=entry.get("setting", "a"), distance_mm=entry.get("distance_mm"),
                                 black_level=entry.get("black_level"), white_level=entry.get("white_level"),
                                 targets=tuple(entry["targets"]) if "targets" in entry else None,
                                 rotate_deg=int(entry.get("rotate_deg", 0))))
    cam = data["camera"]
    if "pixel_pitch_mm" in cam:
        pitch = float(cam["pixel_pitch_mm"])
    elif "sensor_width_mm" in cam:
        pitch = float(cam["sensor_width_mm"]) / shape[1]
    else:
        from lensfit.errors import InputError
        from lensfit.sensors import sensor_format

        try:
            pitch = sensor_format(cam["sensor"]).width_mm / shape[1]
        except InputError as exc:
            raise SpecError(manifest_path, "camera.sensor", f"got {cam['sensor']!r}: unknown; {exc.hint}") from None
    known = {}
    labels = {im.setting for im in images}
    for i, entry in enumerate(data.get("intrinsics", [])):
        if entry["setting"] not in labels:
            raise SpecError(manifest_path, f"intrinsics[{i}].setting", f"got {entry['setting']!r}: no image has this "
                            f"setting; valid: {', '.join(sorted(labels))}")
        known[entry["setting"]] = dict(entry)
    lens = {k: v for k, v in data.get("lens", {}).items() if not k.startswith("x_")}
    if isinstance(lens.get("pupil_magnification"), list):
        lo, hi = lens["pupil_magnification"]
        if not lo < hi:
            raise SpecError(manifest_path, "lens.pupil_magnification", f"got {[lo, hi]}: a range is [lo, hi] with "
                            "lo < hi; give one number where P is known")
        lens["pupil_magnification"] = (float(lo), float(hi))
    return Stack(path=folder, manifest_path=manifest_path, pixel_pitch_mm=pitch, targets=list(data.get("target", [])),
                 images=images, shape=shape, camera=dict(cam), intrinsics=known, max_pixels=max_pixels, lens=lens)
