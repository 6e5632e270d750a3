"""Benchmark suites: what a suite file says (``data_specs/bench/NAME.toml``, schema
``bench.schema.json``) and how its axes are labelled.

A suite is a grid: scenes x render settings x effects x noise levels x estimators x solver
settings x seeds (``lensfit.bench.runs`` runs it, ``lensfit.bench.report`` reports it).
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lensfit.errors import InputError, SpecError
from lensfit.io.specs import load_toml, specs_dir, validate

QUANTITIES = ("focal_length_mm", "f_number", "focus_distance_mm")
DEFAULT_TOLERANCES = {"focal_length_mm": 0.005, "f_number": 0.01, "focus_distance_mm": 0.01}


@dataclass(frozen=True)
class Suite:
    name: str
    description: str
    path: Path
    seeds: tuple[int, ...]
    scenes: tuple[Path, ...]
    renders: tuple[dict[str, Any], ...]
    noises: tuple[dict[str, Any], ...]
    estimators: tuple[str, ...]
    solvers: tuple[dict[str, Any], ...]
    tolerances: dict[str, float]
    effects: tuple[dict[str, Any], ...] = ({"name": "scene"},)

    def tasks(self) -> list[dict[str, Any]]:
        """One task per (scene, render, effects, seed); each lists its cases."""
        out = []
        for scene in self.scenes:
            for render in self.renders:
                for fx in self.effects:
                    for seed in self.seeds:
                        cases = []
                        for noise in self.noises:
                            if "full_well_e" in noise and simulates_sensor(fx):
                                continue  # the effects already made the sensor's noise: not twice
                            for est in self.estimators:
                                for solver in self.solvers:
                                    cases.append({"noise": noise, "estimator": est, "solver": solver})
                        task = {"scene": str(scene), "render": render, "effects": fx, "seed": seed, "cases": cases}
                        for c in cases:
                            c["id"] = case_id(task, c)
                        out.append(task)
        return out


def list_suites() -> list[str]:
    return sorted(p.stem for p in (specs_dir() / "bench").glob("*.toml"))


def load_suite(name_or_path: str | Path) -> Suite:
    """A suite by name (``data_specs/bench/NAME.toml``) or path; validated, scenes resolved."""
    path = Path(name_or_path)
    if not path.suffix:
        path = specs_dir() / "bench" / f"{name_or_path}.toml"
        if not path.is_file():
            raise InputError("suite", str(name_or_path), "one of: " + ", ".join(list_suites()))
    data = load_toml(path)
    validate(data, "bench", path)
    from lensfit.estimators import ESTIMATORS

    for i, est in enumerate(data["estimators"]):
        if est not in ESTIMATORS:
            raise SpecError(path, f"estimators[{i}]", f"{est!r} is not an estimator; use one of {', '.join(ESTIMATORS)}")
    scenes = []
    for i, entry in enumerate(data["scene"]):
        for base in (path.parent, specs_dir() / "scenes"):
            if (base / entry["file"]).is_file():
                scenes.append((base / entry["file"]).resolve())
                break
        else:
            raise SpecError(path, f"scene[{i}].file", f"{entry['file']!r} not found beside the suite or in "
                            "data_specs/scenes/")
    for axis in ("noise", "effects"):
        names = [n["name"] for n in data.get(axis, [])]
        if len(set(names)) != len(names):
            raise SpecError(path, axis, f"{axis} names must be unique")
    effects = tuple(data.get("effects", [{"name": "scene"}]))
    for i, fx in enumerate(effects):  # every scene must accept every effect set: check now, not hours in
        for scene in scenes:
            try:
                scene_with_effects(scene, fx)
            except SpecError as exc:
                raise SpecError(path, f"effects[{i}]", f"{fx['name']!r} does not fit {scene.name}: {exc}") from None
    return Suite(data["name"], data.get("description", ""), path, tuple(data["seeds"]), tuple(scenes),
                 tuple(data["render"]), tuple(data["noise"]), tuple(data["estimators"]), tuple(data["solver"]),
                 {**DEFAULT_TOLERANCES, **data.get("tolerances", {})}, effects)


def simulates_sensor(fx: dict[str, Any]) -> bool:
    """Whether an effect set renders sensor values itself (then no noise level is added on top)."""
    return bool({"exposure", "mosaic"} & set(fx.get("effects", [])))


def scene_with_effects(scene_path: Path, fx: dict[str, Any]):
    """The scene at ``scene_path`` rendered with the effect set ``fx`` (its tables replace the scene's)."""
    from synth.effects import TABLES
    from synth.scene import scene_from_dict

    data = load_toml(scene_path)
    if "effects" in fx:
        for table in TABLES:
            data.pop(table, None)
        data.setdefault("render", {})["effects"] = list(fx["effects"])
        data["render"].pop("format", None)
    for key, value in fx.items():
        if key == "aperture":
            data["lens"]["aperture"] = value
        elif key not in ("name", "effects"):
            data[key] = value
    return scene_from_dict(data, scene_path)


def render_label(render: dict[str, Any]) -> str:
    text = render["method"]
    if "samples_per_pixel" in render:
        text += f" {render['samples_per_pixel']} spp"
    if "supersampling" in render:
        text += f" {render['supersampling']}x ss"
    return text


def solver_label(solver: dict[str, Any]) -> str:
    return (solver["loss"] + (f" floor {solver['blur_floor_px']:g}px" if "blur_floor_px" in solver else "")
            + (f" diffraction {solver['diffraction_nm']:g}nm" if solver.get("diffraction_nm") else "")
            + (" diffraction off" if solver.get("diffraction") == "off" else ""))


def digest_key(*parts: Any) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


#: What a ray-traced render's samples are, in its cache key: a run resumed over renders of another
#: sampler would mix them (digitally shifted Sobol points, synth.raytrace; constant regions taken
#: unsampled, synth.flat).
RAYTRACE_SAMPLER = "sobol-digital-shift+constant-regions"
#: How a render's diffraction met it, in the cache key of an effects set with diffraction: the
#: transfer function filters the geometric render at 4 or 8 times the resolution
#: (synth.effects.diffraction); a render filtered otherwise must not be reused.
DIFFRACTION_RENDER = "fine-4-or-8"


def _render_parts(task: dict[str, Any]) -> tuple:
    fx = task.get("effects", {"name": "scene"})
    parts = (Path(task["scene"]).read_text(), task["render"], task["seed"])
    if task["render"].get("method", "auto") in ("raytrace", "auto"):
        parts += (RAYTRACE_SAMPLER,)
    if "diffraction" in fx.get("effects", ()) or "diffraction" in parts[0]:  # the set's, or the scene's own
        parts += (DIFFRACTION_RENDER,)
    return parts if fx == {"name": "scene"} else parts + (fx,)  # runs without effects keep their ids


def render_key(task: dict[str, Any]) -> str:
    return digest_key(*_render_parts(task))


def case_id(task: dict[str, Any], case: dict[str, Any]) -> str:
    return digest_key(*_render_parts(task), case["noise"], case["estimator"], case["solver"], code_digest())


@functools.cache
def code_digest() -> str:
    """A digest of the lensfit sources that measure and fit: in a case's id, so that a case
    another version (or an edited checkout) measured is not this code's finished case, and a
    resumed run after an upgrade runs it again instead of reporting the old figures as its own."""
    import lensfit

    root = Path(lensfit.__file__).parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]
