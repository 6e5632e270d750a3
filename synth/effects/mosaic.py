"""``mosaic``: a Bayer colour filter array; the stack is written as DNG.

Model
-----
Each photosite keeps one channel of the rendered colour image, in the repeating 2 x 2
``pattern`` (RGGB, BGGR, GRBG or GBRG, read row by row from the top-left pixel). Without
colour effects the scene renders one channel and every site takes it (grey targets give equal
channel signals; white balance 1, 1, 1). The raw frame (DN after ``exposure``, or a 16-bit
linear quantisation without it) is written as a DNG 1.4 file: CFA photometric, the CFA
pattern, black and white levels, an identity colour matrix, and the EXIF focal length,
f-number, exposure time and ISO; rawpy (LibRaw) decodes it to exactly the written values.

Reference: Bayer, US patent 3,971,065 (1976); Adobe *Digital Negative Specification* 1.4.0.0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

NAME = "mosaic"
PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_INDEX = {"R": 0, "G": 1, "B": 2}


@dataclass(frozen=True)
class Mosaic:
    pattern: str = "RGGB"

    def channel_map(self, height_px: int, width_px: int) -> np.ndarray:
        """(H, W) channel index (0 red, 1 green, 2 blue) of each photosite."""
        cell = np.array([[_INDEX[self.pattern[0]], _INDEX[self.pattern[1]]],
                         [_INDEX[self.pattern[2]], _INDEX[self.pattern[3]]]])
        return np.tile(cell, ((height_px + 1) // 2, (width_px + 1) // 2))[:height_px, :width_px]

    def truth(self) -> dict:
        return {"pattern": self.pattern, "file_format": "DNG 1.4 (CFA), decodable by rawpy/LibRaw"}


def apply(image: np.ndarray, params: Mosaic) -> np.ndarray:
    """(H, W) or (H, W, 3) -> (H, W): each site keeps its filter's channel."""
    if image.ndim == 2:
        return image
    idx = params.channel_map(*image.shape[:2])
    return np.take_along_axis(image, idx[..., None], axis=-1)[..., 0]


def write_dng(path: str | Path, raw: np.ndarray, pattern: str, black_level: int, white_level: int,
              exif: dict[str, Any], *, model: str = "lensfit synth") -> None:
    """Write a uint16 CFA frame as DNG (uncompressed), with the camera record ``exif``
    (``synth.rendering.RenderResult.exif``; tags from ``synth.exif``)."""
    import tifffile

    from synth.exif import tiff_extratags

    cfa = tuple(_INDEX[c] for c in pattern)
    identity = []
    for i in range(3):
        for j in range(3):
            identity += [1 if i == j else 0, 1]
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), False),        # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), False),        # DNGBackwardVersion
        (50708, "s", 0, model, False),               # UniqueCameraModel
        (33421, "H", 2, (2, 2), False),              # CFARepeatPatternDim
        (33422, "B", 4, cfa, False),                 # CFAPattern
        (50710, "B", 3, (0, 1, 2), False),           # CFAPlaneColor
        (50711, "H", 1, 1, False),                   # CFALayout: rectangular
        (50713, "H", 2, (1, 1), False),              # BlackLevelRepeatDim
        (50714, "I", 1, int(black_level), False),    # BlackLevel
        (50717, "I", 1, int(white_level), False),    # WhiteLevel
        (50721, "2i", 9, tuple(identity), False),    # ColorMatrix1 (identity: camera = XYZ)
        (50778, "H", 1, 21, False),                  # CalibrationIlluminant1: D65
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), False),  # AsShotNeutral: grey
    ] + tiff_extratags(exif, model)                  # Make, Model, FNumber, FocalLength, ...
    tifffile.imwrite(path, np.ascontiguousarray(raw, np.uint16), photometric=32803, compression=None,
                     extratags=tags, metadata=None)
