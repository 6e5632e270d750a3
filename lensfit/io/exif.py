"""What a camera recorded about a photo: EXIF (and a little of the maker notes) read with exifread.

Read from JPEG, TIFF, DNG and the TIFF-based camera RAW files (CR2, NEF, ARW, PEF, ORF, RW2, ...)
and Fujifilm RAF; fields a file does not hold are None. Nothing here is ever the answer of a fit:
the nominal focal length and f-number are what the lens reports, rounded, and the focus
distance is the camera's coarse estimate. ``lensfit init`` uses them to group photos into
settings and to note them beside each image; the pixel pitch comes from
``FocalPlaneXResolution`` (pixels per unit of the sensor plane) where the camera writes it.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: FocalPlaneResolutionUnit -> millimetres per unit (EXIF 2.32: 2 inch, 3 cm; DNG adds 4 mm, 5 um).
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclass(frozen=True)
class CameraRecord:
    """A photo's EXIF in lensfit's units (None where the file does not say).

    ``focal_plane_pitch_mm``: the sensor pixel pitch from FocalPlaneXResolution, for an image
    ``reference_width_px`` wide (the EXIF PixelXDimension, where the file states it). ``focus_distance_source``: ``"EXIF SubjectDistance"`` or
    ``"Canon maker note"``.
    """

    make: str | None = None
    model: str | None = None
    focal_length_mm: float | None = None
    f_number: float | None = None
    focus_distance_mm: float | None = None
    focus_distance_source: str | None = None
    focal_plane_pitch_mm: float | None = None
    reference_width_px: int | None = None
    shutter_s: float | None = None
    iso: float | None = None
    taken: str | None = None
    #: the program that wrote the file (a camera's firmware, a raw developer)
    software: str | None = None
    #: the lens's widest f-number at this focal length (EXIF MaxApertureValue, an APEX value; else
    #: a prime's LensSpecification)
    widest_f_number: float | None = None

    @property
    def camera(self) -> str | None:
        """``"Make Model"`` without the maker's name said twice (``Canon Canon EOS R5``)."""
        if not self.model:
            return self.make
        if self.make and not self.model.lower().startswith(self.make.split()[0].lower()):
            return f"{self.make} {self.model}"
        return self.model


def _number(value: Any) -> float | None:
    if isinstance(value, (list, tuple)):
        value = value[0] if len(value) == 1 else None
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _text(value: Any) -> str | None:
    if value is None:
        return None
    text = str(value).replace("\x00", "").strip()
    return text or None


def _get(tags: dict[str, Any], name: str) -> Any:
    """A tag from the Exif sub-IFD or IFD0 (DNG and RAW files keep some in IFD0)."""
    for prefix in ("EXIF ", "Image "):
        if prefix + name in tags:
            return tags[prefix + name]
    return None


#: EXIF is read from the file's first bytes only (a JPEG's APP1 segment holds at most 64 kB; RAW
#: files put their IFDs near the start), and maker notes (whose size the file states) only for a
#: Canon body, from its first kilobytes: a maker note of 100 MB, or one claiming 2 GB, kept
#: exifread busy for minutes.
EXIF_READ_BYTES = 8 << 20
MAKER_NOTE_READ_BYTES = 1 << 20


def read_camera_record(path: str | Path) -> CameraRecord:
    """The EXIF of one image file (an empty record where it has none or cannot be parsed)."""
    import logging

    import exifread

    logging.getLogger("exifread").setLevel(logging.CRITICAL)  # (it logs "no exif data" for every PNG)
    try:
        with Path(path).open("rb") as fh:
            head = fh.read(EXIF_READ_BYTES)
        tags = exifread.process_file(io.BytesIO(head), details=False, builtin_types=True, extract_thumbnail=False)
        if _get(tags, "SubjectDistance") is None and (_text(_get(tags, "Make")) or "").lower().startswith("canon"):
            # Canon's focus distance is in its maker note, the one read (from its first kilobytes).
            tags = {**exifread.process_file(io.BytesIO(head[:MAKER_NOTE_READ_BYTES]), details=True,
                                            builtin_types=True, extract_thumbnail=False), **tags}
    except Exception:  # noqa: BLE001 -- exifread raises many kinds on files it does not know
        return CameraRecord()
    return record_from_tags(tags)


def record_from_tags(tags: dict[str, Any]) -> CameraRecord:
    """A :class:`CameraRecord` from exifread's tag dictionary (``builtin_types=True``)."""
    focal = _number(_get(tags, "FocalLength"))
    f_number = _number(_get(tags, "FNumber"))
    focus, source = None, None
    subject = _number(_get(tags, "SubjectDistance"))
    # 0 means unknown; 0xFFFFFFFF (as a rational over 1) means infinity
    if subject is not None and 0.0 < subject < 4.0e9:
        focus, source = 1000.0 * subject, "EXIF SubjectDistance"
    elif subject is not None and subject >= 4.0e9:
        focus, source = math.inf, "EXIF SubjectDistance"
    if focus is None:
        canon = _number(tags.get("MakerNote SubjectDistance"))
        if canon is not None and 0 < canon < 65535:  # centimetres for most Canon bodies
            focus, source = 10.0 * canon, "Canon maker note"
    pitch = None
    widest = None
    apex = _number(_get(tags, "MaxApertureValue"))
    if apex is not None and 0.0 <= apex <= 12.0:  # APEX Av: N = 2 ** (Av / 2), f/1 to f/64
        widest = round(2.0 ** (apex / 2.0), 2)
    spec = _get(tags, "LensSpecification")
    if widest is None and isinstance(spec, (list, tuple)) and len(spec) == 4:
        lo, hi = _number(spec[2]), _number(spec[3])
        if lo and lo == hi and 0.5 <= lo <= 64.0:  # a prime's (a zoom's depends on the focal length)
            widest = lo
    res = _number(_get(tags, "FocalPlaneXResolution"))
    unit = _number(_get(tags, "FocalPlaneResolutionUnit"))
    unit_mm = _UNIT_MM.get(int(unit) if unit is not None else 2)
    if res is not None and res > 0 and unit_mm is not None:
        pitch = unit_mm / res
        if not (1e-4 <= pitch <= 1.0):  # a placeholder, not a sensor
            pitch = None
    # The width FocalPlaneXResolution refers to (EXIF PixelXDimension). Not IFD0's ImageWidth: in
    # many RAW files IFD0 holds a thumbnail.
    width = _number(tags.get("EXIF ExifImageWidth"))
    return CameraRecord(
        make=_text(_get(tags, "Make")), model=_text(_get(tags, "Model")),
        focal_length_mm=focal if focal and focal > 0 else None,
        f_number=f_number if f_number and f_number > 0 else None,
        focus_distance_mm=focus, focus_distance_source=source, focal_plane_pitch_mm=pitch,
        reference_width_px=int(width) if width else None,
        shutter_s=_number(_get(tags, "ExposureTime")), iso=_number(_get(tags, "ISOSpeedRatings")),
        taken=_text(_get(tags, "DateTimeOriginal")), software=_text(_get(tags, "Software")),
        widest_f_number=widest)
