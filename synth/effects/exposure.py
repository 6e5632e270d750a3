"""``exposure``: shutter time, ISO and f-number set the signal; the sensor reads it out.

Model
-----
A scene value v (linear radiance relative to a white surface of luminance ``L``) gives the
sensor exposure (photometric camera equation, ISO 2720 / ISO 12232)

    H = v * (pi/4) * T * L * t * a / N_w^2          (lux seconds)

with lens transmittance ``T``, shutter time ``t``, the aperture's area relative to its circle
``a`` (``synth.effects.aperture``) and the working f-number ``N_w = s / A`` (exposure falls at
close focus: the "bellows factor"). Sensor sensitivity follows the saturation-based ISO speed
of ISO 12232: at the base ISO ``S_0`` an exposure of ``78 / S_0`` lux s fills the full well,
so the mean signal is ``mu_e = H * FW * S_0 / 78`` electrons, plus dark current
``i_d * t``. The readout (here, and in ``synth.effects.noise`` with noise on) is

    DN = clip(round(B + g * min(e, FW)), 0, 2^bits - 1),   g = (2^bits - 1 - B) / FW * S / S_0

(``B`` black level, ``S`` the shot's ISO: gain rises with ISO, so at ISO above base the white
level clips before the full well). Without the ``noise`` effect ``e = mu_e`` exactly: the
image is the mean signal, quantised and clipped, and no random numbers are drawn.

Parameters (``[exposure]``; a shot may override ``shutter_s`` and ``iso``):

=====================  =======  ==========================================  ========
parameter              unit     meaning                                     default
=====================  =======  ==========================================  ========
``shutter_s``          s        exposure time t                             required
``iso``                         ISO speed S                                 base ISO
``luminance_cd_m2``    cd/m^2   luminance L of a scene value of 1           1000
``transmission``                lens transmittance T                        0.9
=====================  =======  ==========================================  ========

The sensor (``[sensor]``): a preset from ``data_specs/sensor_presets.toml`` and/or the fields
full_well_e, read_noise_e, dark_current_e_per_s, bit_depth, black_level_dn, base_iso.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from lensfit.errors import SpecError

NAME = "exposure"
SATURATION_CONSTANT = 78.0  # ISO 12232 saturation-based speed: S = 78 / H_sat


@dataclass(frozen=True)
class Sensor:
    name: str
    full_well_e: float
    read_noise_e: float
    bit_depth: int
    base_iso: float
    black_level_dn: int = 0
    dark_current_e_per_s: float = 0.0

    @property
    def white_level_dn(self) -> int:
        return (1 << self.bit_depth) - 1

    def gain_dn_per_e(self, iso: float) -> float:
        return (self.white_level_dn - self.black_level_dn) / self.full_well_e * iso / self.base_iso

    def electrons_per_lux_s(self) -> float:
        return self.full_well_e * self.base_iso / SATURATION_CONSTANT

    def truth(self) -> dict:
        return {"name": self.name, "full_well_e": self.full_well_e, "read_noise_e": self.read_noise_e,
                "dark_current_e_per_s": self.dark_current_e_per_s, "bit_depth": self.bit_depth,
                "black_level_dn": self.black_level_dn, "white_level_dn": self.white_level_dn,
                "base_iso": self.base_iso}


@functools.lru_cache(maxsize=1)
def presets() -> dict[str, Sensor]:
    from lensfit.io.specs import load_toml, specs_dir, validate

    path = specs_dir() / "sensor_presets.toml"
    data = load_toml(path)
    validate(data, "sensor_presets", path)
    out = {}
    for p in data["preset"]:
        out[p["name"]] = Sensor(name=p["name"], full_well_e=float(p["full_well_e"]),
                                read_noise_e=float(p["read_noise_e"]), bit_depth=int(p["bit_depth"]),
                                base_iso=float(p["base_iso"]), black_level_dn=int(p.get("black_level_dn", 0)),
                                dark_current_e_per_s=float(p.get("dark_current_e_per_s", 0.0)))
    return out


FIELDS = ("full_well_e", "read_noise_e", "bit_depth", "base_iso", "black_level_dn", "dark_current_e_per_s")


def sensor_from_spec(spec: dict | None, path) -> Sensor:
    """``[sensor]``: a preset, fields overriding it, or every field given."""
    spec = dict(spec or {})
    if "preset" in spec:
        name = spec.pop("preset")
        if name not in presets():
            raise SpecError(path, "sensor.preset", f"got {name!r}: unknown; valid: {', '.join(presets())}")
        base = presets()[name]
        return replace(base, **{k: type(getattr(base, k))(v) for k, v in spec.items() if k in FIELDS})
    missing = [k for k in ("full_well_e", "read_noise_e", "bit_depth", "base_iso") if k not in spec]
    if missing:
        raise SpecError(path, "sensor", f"needs preset = NAME ({', '.join(presets())}) or the fields "
                        f"{', '.join(missing)}")
    return Sensor(name=spec.get("name", "custom"), full_well_e=float(spec["full_well_e"]),
                  read_noise_e=float(spec["read_noise_e"]), bit_depth=int(spec["bit_depth"]),
                  base_iso=float(spec["base_iso"]), black_level_dn=int(spec.get("black_level_dn", 0)),
                  dark_current_e_per_s=float(spec.get("dark_current_e_per_s", 0.0)))


@dataclass(frozen=True)
class Exposure:
    shutter_s: float
    iso: float | None = None  # None: the sensor's base ISO
    luminance_cd_m2: float = 1000.0
    transmission: float = 0.9

    def for_shot(self, shutter_s=None, iso=None) -> "Exposure":
        return replace(self, shutter_s=self.shutter_s if shutter_s is None else float(shutter_s),
                       iso=self.iso if iso is None else float(iso))


def lux_seconds_per_unit(exposure: Exposure, working_f_number: float, area_fraction: float = 1.0) -> float:
    """Sensor exposure H (lux s) of a scene value of 1."""
    return math.pi / 4 * exposure.transmission * exposure.luminance_cd_m2 * exposure.shutter_s * area_fraction \
        / working_f_number**2


def mean_electrons(image: np.ndarray, exposure: Exposure, sensor: Sensor, working_f_number: float,
                   area_fraction: float = 1.0) -> np.ndarray:
    """Mean signal in electrons (float64), dark current included."""
    per_unit = lux_seconds_per_unit(exposure, working_f_number, area_fraction) * sensor.electrons_per_lux_s()
    return np.asarray(image, np.float64) * per_unit + sensor.dark_current_e_per_s * exposure.shutter_s


def readout(electrons: np.ndarray, sensor: Sensor, iso: float, read_noise_e: np.ndarray | None = None) -> np.ndarray:
    """Electrons -> raw DN (uint16): full-well clip, gain, black level, rounding, white clip."""
    e = np.minimum(electrons, sensor.full_well_e)
    if read_noise_e is not None:
        e = e + read_noise_e
    dn = np.rint(sensor.black_level_dn + sensor.gain_dn_per_e(iso) * e)
    return np.clip(dn, 0, sensor.white_level_dn).astype(np.uint16)


def truth(exposure: Exposure, sensor: Sensor, working_f_number: float, area_fraction: float) -> dict:
    iso = exposure.iso if exposure.iso is not None else sensor.base_iso
    H = lux_seconds_per_unit(exposure, working_f_number, area_fraction)
    return {"shutter_s": exposure.shutter_s, "iso": iso, "luminance_cd_m2": exposure.luminance_cd_m2,
            "transmission": exposure.transmission, "working_f_number": working_f_number,
            "lux_seconds_per_unit": H, "electrons_per_unit": H * sensor.electrons_per_lux_s(),
            "gain_dn_per_e": sensor.gain_dn_per_e(iso), "black_level_dn": sensor.black_level_dn,
            "white_level_dn": sensor.white_level_dn,
            "dark_electrons": sensor.dark_current_e_per_s * exposure.shutter_s}


def seconds(width_px: int, height_px: int) -> float:
    """Rough cost on 2 cores (measured ~4 ms per megapixel)."""
    return 5e-9 * width_px * height_px
