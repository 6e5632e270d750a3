"""What a camera writes into its files: EXIF tags for synth's DNG and JPEG images.

One list of tags (:func:`exif_entries`) written two ways: into a DNG's first IFD by tifffile
(:func:`tiff_extratags`), into a JPEG's APP1 block by Pillow (:func:`pillow_exif`). Values are a
camera's nominal ones (``synth.rendering.RenderResult.exif``): focal length, f-number, the focus
distance as ``SubjectDistance`` (metres), the pixel pitch as ``FocalPlaneXResolution`` (pixels
per centimetre; EXIF 2.32, tag 0xA20E), exposure time and ISO where the exposure effect sets them,
and a compound lens's widest f-number as ``MaxApertureValue`` (APEX, ``2 log2 N``).
``lensfit init`` reads them back (``lensfit.io.exif``).
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Any

MAKE = "lensfit"
MODEL = "lensfit synth"

# (tag, name, TIFF type) of the tags written; "ascii", "rational" or "short".
_TAGS = {
    "make": (0x010F, "Make", "ascii"),
    "model": (0x0110, "Model", "ascii"),
    "shutter_s": (0x829A, "ExposureTime", "rational"),
    "f_number": (0x829D, "FNumber", "rational"),
    "iso": (0x8827, "ISOSpeedRatings", "short"),
    "subject_distance_m": (0x9206, "SubjectDistance", "rational"),
    "focal_length_mm": (0x920A, "FocalLength", "rational"),
    "focal_plane_x_resolution": (0xA20E, "FocalPlaneXResolution", "rational"),
    "focal_plane_y_resolution": (0xA20F, "FocalPlaneYResolution", "rational"),
    "focal_plane_resolution_unit": (0xA210, "FocalPlaneResolutionUnit", "short"),
    "max_aperture_apex": (0x9205, "MaxApertureValue", "rational"),
}
#: Tags that live in IFD0 of a JPEG (the others go to its Exif sub-IFD).
_IFD0 = {"make", "model"}


def _rational(x: float, max_den: int = 1_000_000) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(max_den)
    return f.numerator, f.denominator


def exif_entries(exif: dict[str, Any], model: str = MODEL) -> list[tuple[str, Any]]:
    """(key of ``_TAGS``, value) for a shot's camera record."""
    out: list[tuple[str, Any]] = [("make", MAKE), ("model", model),
                                  ("focal_length_mm", float(exif["focal_length_mm"])),
                                  ("f_number", float(exif["f_number"]))]
    if exif.get("focus_distance_mm") is not None:
        out.append(("subject_distance_m", float(exif["focus_distance_mm"]) / 1000.0))
    if exif.get("pixel_pitch_mm"):
        per_cm = 10.0 / float(exif["pixel_pitch_mm"])
        out += [("focal_plane_x_resolution", per_cm), ("focal_plane_y_resolution", per_cm),
                ("focal_plane_resolution_unit", 3)]  # 3 = centimetre
    if exif.get("shutter_s") is not None:
        out.append(("shutter_s", float(exif["shutter_s"])))
    if exif.get("iso") is not None:
        out.append(("iso", int(round(exif["iso"]))))
    if exif.get("widest_f_number"):  # a compound lens's full aperture, as an APEX value
        out.append(("max_aperture_apex", 2.0 * math.log2(float(exif["widest_f_number"]))))
    return out


def tiff_extratags(exif: dict[str, Any], model: str = MODEL) -> list[tuple]:
    """tifffile ``extratags`` for a DNG's IFD0."""
    tags = []
    for key, value in exif_entries(exif, model):
        code, _, kind = _TAGS[key]
        if kind == "ascii":
            tags.append((code, "s", 0, value, False))
        elif kind == "rational":
            tags.append((code, "2I", 1, _rational(value), False))
        else:
            tags.append((code, "H", 1, int(value), False))
    return tags


def pillow_exif(exif: dict[str, Any], model: str = MODEL):
    """A ``PIL.Image.Exif`` for ``Image.save(..., exif=...)``."""
    from PIL import Image
    from PIL.ExifTags import IFD
    from PIL.TiffImagePlugin import IFDRational

    out = Image.Exif()
    sub = out.get_ifd(IFD.Exif)
    for key, value in exif_entries(exif, model):
        code, _, kind = _TAGS[key]
        target = out if key in _IFD0 else sub
        target[code] = IFDRational(*_rational(value)) if kind == "rational" else value
    return out
