"""Effects: the stages a scene may call for after the geometric (defocus) render.

``render.effects`` lists them; each has one module here with its model, parameters (units)
and reference; its stage (what it costs, what it does to the image, what it records in the
truth) is registered in ``synth.effects.stages``; its parameters are in a table of the same name in the scene (``[diffraction]``,
``[vignetting]``, ``[distortion]``, ``[chromatic_aberration]``, ``[exposure]`` with
``[sensor]``, ``[noise]``, ``[mosaic]``; the aperture's shape is ``lens.aperture``). An effect
that is not listed has no stage: its code is not called, it draws no random numbers and costs
nothing. The pipeline, in the order light meets them:

    defocus (aperture shape, optical vignetting, per-channel focus of longitudinal CA)
    -> diffraction -> vignetting (cos^4) -> distortion + lateral CA (one resampling)
    -> exposure (electrons) -> mosaic (CFA) -> noise -> readout (DN)  |  quantise (16-bit)

A scene renders three channels (red, green, blue) only when an effect makes them differ:
chromatic aberration, or diffraction with three wavelengths (given, or implied by a mosaic),
or when a spectral compound lens is asked for colour (``[lens] colour``, ``synth.spectral``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lensfit.errors import SpecError
from synth.effects.aperture import Aperture
from synth.effects.chromatic_aberration import ChromaticAberration
from synth.effects.diffraction import DEFAULT_RGB_NM, DEFAULT_WAVELENGTH_NM, Diffraction
from synth.effects.distortion import Distortion
from synth.effects.exposure import Exposure, Sensor, sensor_from_spec
from synth.effects.mosaic import Mosaic
from synth.effects.noise import Noise
from synth.effects.vignetting import Vignetting

#: Every effect, in pipeline order.
ORDER = ("defocus", "aperture", "diffraction", "vignetting", "distortion", "chromatic_aberration",
         "exposure", "mosaic", "noise")
#: Scene tables that hold effect parameters, and the effect each belongs to.
TABLES = {"diffraction": "diffraction", "vignetting": "vignetting", "distortion": "distortion",
          "chromatic_aberration": "chromatic_aberration", "exposure": "exposure", "sensor": "exposure",
          "noise": "noise", "mosaic": "mosaic"}


@dataclass(frozen=True)
class Effects:
    """The effects a scene calls for, with their parameters (None: not called for)."""

    names: tuple[str, ...] = ("defocus",)
    aperture: Aperture = Aperture()
    diffraction: Diffraction | None = None
    vignetting: Vignetting | None = None
    distortion: Distortion | None = None
    chromatic_aberration: ChromaticAberration | None = None
    exposure: Exposure | None = None
    sensor: Sensor | None = None
    noise: Noise | None = None
    mosaic: Mosaic | None = None
    #: The scene asks for colour from spectral samples (``[lens] colour``, ``synth.spectral``).
    colour: bool = False

    @property
    def channels(self) -> int:
        """1, or 3 when an effect makes the colour channels differ or the scene asks for colour."""
        if self.colour or self.chromatic_aberration is not None:
            return 3
        if self.diffraction is not None and len(self.diffraction.wavelength_nm) == 3:
            return 3
        return 1

    @property
    def needs_raytrace(self) -> str | None:
        """Why only ray tracing can render these effects, or None."""
        if self.vignetting is not None and self.vignetting.optical:
            return "optical vignetting (the front stop clips each pixel's pupil differently)"
        return None

    def format_problem(self, fmt: str) -> tuple[str, str] | None:
        """(what the image format must be, why) when ``fmt`` cannot hold these effects' output."""
        if self.mosaic is not None and fmt != "dng":
            return "dng", "the mosaic effect writes DNG"
        if fmt == "dng" and self.mosaic is None:
            return "png, tiff or float-tiff", "DNG holds a Bayer mosaic: add 'mosaic' to render.effects"
        if fmt == "float-tiff" and self.exposure is not None:
            return "png or tiff", "the exposure effect produces integer sensor values (DN)"
        return None

    def truth(self) -> dict[str, Any]:
        """Parameters of every effect called for (per-shot quantities are in each image's entry)."""
        out: dict[str, Any] = {"aperture": self.aperture.truth()}
        if self.diffraction is not None:
            out["diffraction"] = {"wavelength_nm": list(self.diffraction.wavelength_nm),
                                  "reach_rings": self.diffraction.reach_rings}
        if self.vignetting is not None:
            out["vignetting"] = self.vignetting.truth()
        if self.distortion is not None:
            out["distortion"] = self.distortion.truth()
        if self.chromatic_aberration is not None:
            ca = self.chromatic_aberration
            out["chromatic_aberration"] = {"focal_shift_mm": list(ca.focal_shift_mm),
                                           "magnification": list(ca.magnification)}
        if self.sensor is not None:
            out["sensor"] = self.sensor.truth()
        if self.noise is not None:
            out["noise"] = self.noise.truth()
        if self.mosaic is not None:
            out["mosaic"] = self.mosaic.truth()
        out["channels"] = ["red", "green", "blue"] if self.channels == 3 else ["grey"]
        return out


def _triple(value, path, field: str, neutral: float) -> tuple[float, float, float]:
    if len(value) != 3:
        raise SpecError(path, field, f"got {value}: give three values, [red, green, blue]")
    if float(value[1]) != neutral:
        raise SpecError(path, f"{field}[1]", f"got {value[1]}: green is the reference channel; set it to {neutral:g}")
    return tuple(float(v) for v in value)  # type: ignore[return-value]


def parse(data: dict[str, Any], path: str | Path, names: tuple[str, ...], aperture_spec: dict) -> Effects:
    """Effects and their parameters from a scene dict; every inconsistency is a SpecError."""
    if not names or names[0] != "defocus":
        raise SpecError(path, "render.effects", f"got {list(names)}: the list starts with 'defocus' (the geometric "
                        "render every other effect acts on)")
    for table, effect in TABLES.items():
        if table in data and effect not in names:
            raise SpecError(path, table, f"[{table}] is given but {effect!r} is not in render.effects; add it there "
                            "or remove the table")
    aperture = Aperture.from_spec(aperture_spec)
    if aperture.shape != "circle" and "aperture" not in names:
        raise SpecError(path, "lens.aperture", f"got shape {aperture.shape!r} but 'aperture' is not in render.effects; "
                        "add it there (or use aperture = \"circle\")")
    out: dict[str, Any] = {"names": tuple(names), "aperture": aperture}

    if "chromatic_aberration" in names:
        t = data.get("chromatic_aberration", {})
        if not t:
            raise SpecError(path, "chromatic_aberration", "give focal_shift_mm = [r, 0, b] and/or magnification = "
                            "[r, 1, b]")
        out["chromatic_aberration"] = ChromaticAberration(
            focal_shift_mm=_triple(t.get("focal_shift_mm", [0, 0, 0]), path, "chromatic_aberration.focal_shift_mm", 0.0),
            magnification=_triple(t.get("magnification", [1, 1, 1]), path, "chromatic_aberration.magnification", 1.0))
    spectral_colour = bool(data.get("lens", {}).get("colour", False))
    if spectral_colour:
        out["colour"] = True
    colour = "chromatic_aberration" in names or "mosaic" in names or spectral_colour
    if "diffraction" in names:
        t = data.get("diffraction", {})
        w = t.get("wavelength_nm", list(DEFAULT_RGB_NM) if colour else DEFAULT_WAVELENGTH_NM)
        w = tuple(float(v) for v in w) if isinstance(w, list) else (float(w),)
        if len(w) not in (1, 3):
            raise SpecError(path, "diffraction.wavelength_nm", f"got {list(w)}: one wavelength, or three [r, g, b]")
        if "chromatic_aberration" in names and len(w) == 1:
            w = (w[0],) * 3
        out["diffraction"] = Diffraction(wavelength_nm=w, reach_rings=int(t.get("reach_rings", 12)))
    if "vignetting" in names:
        t = data.get("vignetting", {})
        has = [k in t for k in ("front_stop_distance_mm", "front_stop_diameter_mm")]
        if any(has) and not all(has):
            raise SpecError(path, "vignetting", "optical vignetting needs both front_stop_distance_mm and "
                            "front_stop_diameter_mm")
        out["vignetting"] = Vignetting(natural=bool(t.get("natural", True)),
                                       front_stop_distance_mm=t.get("front_stop_distance_mm"),
                                       front_stop_diameter_mm=t.get("front_stop_diameter_mm"))
    if "distortion" in names:
        t = data.get("distortion", {})
        if not any(k in t for k in ("k1", "k2", "k3", "p1", "p2")):
            raise SpecError(path, "distortion", "give at least one of k1, k2, k3, p1, p2 (OpenCV's convention)")
        out["distortion"] = Distortion(**{k: float(t.get(k, 0.0)) for k in ("k1", "k2", "k3", "p1", "p2")})
    if "noise" in names and "exposure" not in names:
        raise SpecError(path, "render.effects", "'noise' needs 'exposure' (noise is counted in electrons); add "
                        "'exposure' and an [exposure] table")
    if "exposure" in names:
        t = data.get("exposure")
        if not t or "shutter_s" not in t:
            raise SpecError(path, "exposure.shutter_s", "is required when 'exposure' is in render.effects")
        out["exposure"] = Exposure(shutter_s=float(t["shutter_s"]), iso=t.get("iso"),
                                   luminance_cd_m2=float(t.get("luminance_cd_m2", 1000.0)),
                                   transmission=float(t.get("transmission", 0.9)))
        if "sensor" not in data:
            from synth.effects.exposure import presets

            raise SpecError(path, "sensor", f"is required with 'exposure': preset = NAME ({', '.join(presets())}) "
                            "or the sensor's fields")
        out["sensor"] = sensor_from_spec(data["sensor"], path)
    if "noise" in names:
        t = data.get("noise", {})
        out["noise"] = Noise(shot=bool(t.get("shot", True)), read=bool(t.get("read", True)))
    if "mosaic" in names:
        out["mosaic"] = Mosaic(pattern=data.get("mosaic", {}).get("pattern", "RGGB"))
    return Effects(**out)
