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
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.errors import SpecError
from lensfit.io.images import JPEG_SUFFIXES, HeldRaster, image_size, read_image, read_inside
from lensfit.io.specs import load_toml, validate

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
    #: ``focusing``, unit, internal or unknown; ``ideal``, a lens without aberrations;
    #: ``widest_f_number``, its full aperture)
    lens: dict[str, Any] = field(default_factory=dict)
    #: images kept in memory once read (None: read again each time; :meth:`holding`)
    hold: "ImageHold | None" = field(default=None, repr=False, compare=False)
    #: image files may lie outside the folder (``--allow-outside-stack``); otherwise each is read
    #: from a descriptor checked to lie inside it (``lensfit.io.images.read_inside``)
    outside_allowed: bool = False

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
        """This stack keeping its images in memory once read (:attr:`hold`): as float64 where all
        of them fit in ``limit_bytes`` so; else, up to ``COMPACT_HOLD_SHARE`` of it, as their
        files' integers where they are single-channel integer images (16-bit PNG or TIFF: a
        quarter of the bytes), made linear again on each read (a 24 MP image in 0.2 s, against
        0.5 s decoded anew); this stack itself where it holds them already."""
        if self.hold is not None:
            return self
        whole = len(self.images) * self.shape[0] * self.shape[1] * 8 <= limit_bytes
        return replace(self, hold=ImageHold(limit_bytes if whole else int(limit_bytes * COMPACT_HOLD_SHARE),
                                            compact=not whole))

    def read(self, index: int) -> np.ndarray:
        """Image ``index`` as linear float64 intensity (H, W), full scale 1 (where the stack holds
        its images as float64, the one array read first: not to be modified)."""
        if self.hold is not None and (held := self.hold.get(index)) is not None:
            return held.linear() if isinstance(held, HeldRaster) else held
        entry = self.images[index]
        data = None if self.outside_allowed else read_inside(entry.file, self.path, self.max_pixels)
        image = read_image(entry.file, entry.encoding, black_level=entry.black_level, white_level=entry.white_level,
                           max_pixels=self.max_pixels, data=data, keep_integers=self.hold is not None and
                           self.hold.compact)
        if entry.rotate_deg:
            image = (image.rotated(entry.rotate_deg // 90) if isinstance(image, HeldRaster) else
                     np.ascontiguousarray(np.rot90(image, entry.rotate_deg // 90)))
        if self.hold is not None:
            self.hold.put(index, image)
        return image.linear() if isinstance(image, HeldRaster) else image


#: The share of a stack's memory budget that its images may be held in as integers where they do
#: not fit as float64: the rest is left to the work on them (a 45 MP image being searched takes
#: about 1 GB), so that the whole run stays within its budget.
COMPACT_HOLD_SHARE = 0.375


class ImageHold:
    """Images kept in memory once read, within ``limit_bytes``: float64 arrays, or with
    ``compact`` their files' integers (:class:`lensfit.io.images.HeldRaster`) where they are so
    (others are read again each time). Safe to fill from the threads that read the images."""

    def __init__(self, limit_bytes: int, compact: bool = False):
        self.limit_bytes, self.compact = limit_bytes, compact
        self._images: dict[int, Any] = {}
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, index: int) -> Any:
        return self._images.get(index)

    def put(self, index: int, image: Any) -> bool:
        """Keep ``image`` where it fits (a float64 array kept only by a hold that is not compact);
        whether it was kept."""
        if self.compact != isinstance(image, HeldRaster):
            return False
        with self._lock:
            if index in self._images or self._bytes + image.nbytes > self.limit_bytes:
                return index in self._images
            self._images[index] = image
            self._bytes += image.nbytes
            return True


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
    from lensfit.calibration.targets import aruco_dictionary, aruco_dictionary_names

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
    max_pixels : refuse images declaring more pixels (default ``lensfit.io.limits.DEFAULT_MAX_MEGAPIXELS``)
    allow_outside : read image files outside the stack folder (``../``, absolute paths, symbolic
        links that lead out); refused by default, naming the entry
    """
    from lensfit.io.limits import DEFAULT_MAX_MEGAPIXELS, check_image_size

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
        from lensfit.io.sensors import sensor_format

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
                 images=images, shape=shape, camera=dict(cam), intrinsics=known, max_pixels=max_pixels, lens=lens,
                 outside_allowed=allow_outside)
