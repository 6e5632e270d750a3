"""Prescription files: the shipped designs (``data_specs/lenses``), inline tables and the glass
catalogue (``data_specs/glasses.toml``)."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any


from lensfit.errors import SpecError
from synth.lens.prescription import Glass, Prescription, Surface, paraxial



def lens_dir() -> Path:
    from lensfit.io.specs import specs_dir

    return specs_dir() / "lenses"


def list_prescriptions() -> list[str]:
    return sorted(p.stem for p in lens_dir().glob("*.toml"))


def prescription_from_dict(data: dict[str, Any], path: str | Path = "<lens>") -> Prescription:
    """A prescription from its table (a lens file, or an inline ``[lens] surface = [...]``)."""
    rows = data.get("surface")
    if not isinstance(rows, list) or len(rows) < 2:
        raise SpecError(path, "surface", "needs a list of at least two surfaces, front to back")
    surfaces = []
    for i, r in enumerate(rows):
        where = f"surface[{i}]"
        if not isinstance(r, dict):
            raise SpecError(path, where, "must be a table with radius_mm, thickness_mm, n, semi_aperture_mm")
        unknown = set(r) - {"radius_mm", "thickness_mm", "n", "V", "glass", "semi_aperture_mm", "stop"}
        if unknown:
            raise SpecError(path, f"{where}.{sorted(unknown)[0]}", "unknown field; valid: radius_mm, thickness_mm, "
                            "n, V, glass, semi_aperture_mm, stop")
        glass = None
        if "glass" in r:
            glass = _glass(r["glass"], path, f"{where}.glass")
            if "V" in r:
                raise SpecError(path, f"{where}.V", "conflicts with glass (whose dispersion it is); remove one")
            if "n" not in r:
                r = {**r, "n": round(glass.nd, 6)}
            elif isinstance(r["n"], (int, float)) and abs(r["n"] - glass.nd) > 1e-3:
                raise SpecError(path, f"{where}.n", f"got {r['n']}: {glass.name} has n_d {glass.nd:.5f}; give that "
                                "index or drop n")
        for name in ("radius_mm", "thickness_mm", "n", "semi_aperture_mm"):
            if name not in r:
                raise SpecError(path, f"{where}.{name}", "is required but missing")
        radius = math.inf if r["radius_mm"] in ("inf", "-inf") else r["radius_mm"]
        if not isinstance(radius, (int, float)) or radius == 0 or not math.isfinite(abs(radius) if radius != math.inf
                                                                                    else 1.0):
            raise SpecError(path, f"{where}.radius_mm", f"got {r['radius_mm']!r}: a non-zero number of mm or \"inf\"")
        checks = (("thickness_mm", r["thickness_mm"], 0.0, 1e5), ("n", r["n"], 1.0, 4.0),
                  ("semi_aperture_mm", r["semi_aperture_mm"], 1e-6, 1e4))
        for name, v, lo, hi in checks:
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not (math.isfinite(v) and lo <= v <= hi):
                raise SpecError(path, f"{where}.{name}", f"got {v!r}: must be a number from {lo:g} to {hi:g}")
        if math.isfinite(radius) and abs(radius) < r["semi_aperture_mm"]:
            raise SpecError(path, f"{where}.semi_aperture_mm", f"got {r['semi_aperture_mm']}: larger than the "
                            f"radius of curvature ({radius}); no sphere is that wide")
        abbe = r.get("V")
        if abbe is not None and not (isinstance(abbe, (int, float)) and 10 <= abbe <= 120):
            raise SpecError(path, f"{where}.V", f"got {abbe!r}: an Abbe number from 10 to 120")
        surfaces.append(Surface(float(radius), float(r["thickness_mm"]), float(r["n"]), float(r["semi_aperture_mm"]),
                                bool(r.get("stop", False)), None if abbe is None else float(abbe), glass))
    stops = [i for i, s in enumerate(surfaces) if s.stop]
    if len(stops) != 1:
        raise SpecError(path, "surface", f"exactly one surface must have stop = true, found {len(stops)}")
    if surfaces[-1].n != 1.0:
        raise SpecError(path, f"surface[{len(surfaces) - 1}].n", "the last surface must leave the lens into air (n = 1)")
    rx = Prescription(str(data.get("name", Path(str(path)).stem)), tuple(surfaces), str(data.get("source", "")),
                      data.get("design_f_number"))
    para = paraxial(rx)
    if not (math.isfinite(para.efl_mm) and para.efl_mm > 0):
        raise SpecError(path, "surface", f"the lens has no positive focal length (EFL {para.efl_mm:.4g} mm); "
                        "check the signs of the radii (> 0: centre of curvature behind the surface)")
    return rx


@functools.cache
def glass_catalogue() -> dict[str, Glass]:
    """The glasses of ``data_specs/glasses.toml`` by name."""
    from lensfit.io.specs import load_toml, specs_dir

    return {name: Glass(name, tuple(g["B"]), tuple(g["C_um2"]), "SCHOTT Zemax catalogue 2017-01-20b")
            for name, g in load_toml(specs_dir() / "glasses.toml")["glass"].items()}


def _glass(name, path, where: str) -> Glass:
    catalogue = glass_catalogue()
    if not isinstance(name, str) or name not in catalogue:
        import difflib

        close = difflib.get_close_matches(str(name).upper(), list(catalogue), n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise SpecError(path, where, f"got {name!r}: not in data_specs/glasses.toml; {hint}known: "
                        f"{', '.join(sorted(catalogue))} (or give n and V)")
    return catalogue[name]


def load_prescription(name: str | Path) -> Prescription:
    """A shipped design by name (``data_specs/lenses/NAME.toml``) or the path of a lens file."""
    from lensfit.io.specs import load_toml

    path = Path(name)
    if path.suffix != ".toml":
        path = lens_dir() / f"{name}.toml"
        if not path.is_file():
            raise SpecError("lens.prescription", "", f"got {name!r}: no such design; shipped: "
                            f"{', '.join(list_prescriptions())} (or the path of a lens .toml)")
    return prescription_from_dict(load_toml(path), path)
