"""Named sensor formats (``data_specs/sensor_formats.toml``)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

from lensfit.errors import InputError
from lensfit.io.specs import load_toml, specs_dir, validate


@dataclass(frozen=True)
class SensorFormat:
    """A sensor's active area, and its pixel grid where known.

    Attributes
    ----------
    name : str
        Canonical name, e.g. ``"full-frame"``.
    width_mm, height_mm : float
        Active-area size, mm.
    resolution_px : tuple[int, int] or None
        (width, height) in pixels, when the format fixes it.
    chart_crop_factor : float or None
        Crop factor printed in the course's chart (reference data for tests).
    source : str
        Where the size comes from.
    """

    name: str
    width_mm: float
    height_mm: float
    resolution_px: tuple[int, int] | None = None
    chart_crop_factor: float | None = None
    aliases: tuple[str, ...] = ()
    source: str = ""

    @property
    def diagonal_mm(self) -> float:
        return (self.width_mm**2 + self.height_mm**2) ** 0.5

    @property
    def pixel_pitch_mm(self) -> float | None:
        """Pixel pitch (mm) from width and resolution, or None when the resolution is unknown."""
        return None if self.resolution_px is None else self.width_mm / self.resolution_px[0]


@functools.cache
def sensor_formats() -> dict[str, SensorFormat]:
    """All formats by canonical name (validated against their schema on first use)."""
    path = specs_dir() / "sensor_formats.toml"
    data = load_toml(path)
    validate(data, "sensor_formats", path)
    out: dict[str, SensorFormat] = {}
    for entry in data["format"]:
        res = entry.get("resolution_px")
        out[entry["name"]] = SensorFormat(
            name=entry["name"], width_mm=float(entry["width_mm"]), height_mm=float(entry["height_mm"]),
            resolution_px=tuple(res) if res else None, chart_crop_factor=entry.get("chart_crop_factor"),
            aliases=tuple(entry.get("aliases", ())), source=entry.get("source", ""))
    return out


def sensor_format(name: str, argument: str = "sensor") -> SensorFormat:
    """Look up a format by name or alias (case-insensitive).

    Raises
    ------
    InputError
        Unknown name; the message lists the valid names.
    """
    key = name.strip().lower()
    for fmt in sensor_formats().values():
        if key == fmt.name or key in fmt.aliases:
            return fmt
    raise InputError(argument, name, "a known sensor format",
                     "valid: " + ", ".join(sensor_formats()))
