"""Benchmark on real (thick, aberrated) lenses: stacks ray traced through every shipped
prescription (``data_specs/lenses``), fitted as a thin lens and as a thick lens.

Each lens gets the demo's calibration stack (``data_specs/scenes/demo.toml``: two ChArUco
boards at 0.5 to 3 times the focus distance, seven of twelve views tilted) with every length,
the pixel pitch included, scaled by f / 25 mm, so that field of view and blur in pixels are the
demo's at the same f-number; rendered at two focus distances (X and 2X, unit focusing), 600 x
400 px. Three fits per lens:

- ``thin (one setting)``: the first setting alone, the pupil magnification P assumed 1 (what a
  thin-lens tool reports);
- ``thick, P given``: the first setting alone, P given as the prescription's (an assumption a
  user with the lens data can make);
- ``thick (bracket)``: both settings, P fitted.

Errors are against the prescription's paraxial data (EFL, f-number = EFL / entrance-pupil
diameter, focus distance from the entrance pupil), recorded in each stack's truth.json.
"""

from __future__ import annotations

import copy
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from lensfit.fitting import fit
from lensfit.measure import measure
from lensfit.specs import load_toml, specs_dir

LENGTH_KEYS = ("distance_mm", "square_mm", "marker_mm", "size_mm", "offset_mm", "pixel_pitch_mm", "focus_distance_mm")


def _scaled(value: Any, k: float) -> Any:
    if isinstance(value, list):
        return [_scaled(v, k) for v in value]
    return value * k if isinstance(value, (int, float)) and not isinstance(value, bool) else value


def _scale_lengths(node: Any, k: float) -> Any:
    if isinstance(node, dict):
        return {key: (_scaled(v, k) if key in LENGTH_KEYS else _scale_lengths(v, k)) for key, v in node.items()}
    if isinstance(node, list):
        return [_scale_lengths(v, k) for v in node]
    return node


def lens_scene(name: str, f_number: float = 11.0, spp: int = 64) -> dict[str, Any]:
    """The demo scene scaled to the prescription ``name``, shot at focus X and 2X."""
    from synth.lens import load_prescription, paraxial

    efl = paraxial(load_prescription(name)).efl_mm
    demo = load_toml(specs_dir() / "scenes" / "demo.toml")
    k = efl / demo["lens"]["focal_length_mm"]
    scene = _scale_lengths(copy.deepcopy(demo), k)
    scene["camera"].update(width_px=600, height_px=400, pixel_pitch_mm=2 * demo["camera"]["pixel_pitch_mm"] * k)
    focus = scene["lens"]["focus_distance_mm"]
    scene["lens"] = {"prescription": name, "f_number": f_number, "focus_distance_mm": focus}
    scene["render"] = {"effects": ["defocus"], "method": "raytrace", "samples_per_pixel": spp, "seed": 0}
    shots = scene["shot"]
    scene["shot"] = ([{**s, "setting": "near"} for s in shots]
                     + [{**s, "setting": "far", "focus_distance_mm": 2 * focus, "name": f"far_{i:03d}"}
                        for i, s in enumerate(shots)])
    scene["name"] = f"{name}-bracket"
    return scene


def _errors(result, truth: dict[str, Any], label: str) -> dict[str, Any]:
    t = truth["settings"][label]
    out = {}
    for q, tv in (("focal_length_mm", truth["focal_length_mm"]), ("f_number", t["f_number"]),
                  ("focus_distance_mm", t["focus_distance_mm"])):
        e = result.settings[label][q]
        out[q] = {"estimate": e.value, "truth": tv, "relative_error": None if e.value is None else e.value / tv - 1,
                  "within_ci95": None if e.ci95 is None else bool(
                      (e.ci95[0] is None or e.ci95[0] <= tv) and (e.ci95[1] is None or tv <= e.ci95[1]))}
    return out


def run(names: list[str] | None = None, spp: int = 64,
        progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Render, measure and fit every lens; returns rows of errors and seconds."""
    import json

    from synth.lens import list_prescriptions
    from synth.render import render
    from synth.scene import scene_from_dict
    from synth.stack import write_stack

    say = progress or (lambda msg: None)
    rows = []
    with tempfile.TemporaryDirectory(prefix="lensfit-bench-lenses-") as tmp:
        for name in names or list_prescriptions():
            say(f"{name}: rendering 24 shots")
            t0 = time.perf_counter()
            scene = scene_from_dict(lens_scene(name, spp=spp), f"<{name} bracket>")
            folder = write_stack(render(scene), Path(tmp) / name)
            t_render = time.perf_counter() - t0
            truth = json.loads((folder / "truth.json").read_text())
            say(f"{name}: measuring")
            t0 = time.perf_counter()
            table = measure(folder)
            t_measure = time.perf_counter() - t0
            near = [s for s in table.samples if s.setting == "near"]
            one = copy.copy(table)
            one.samples = near
            one.intrinsics = {"near": table.intrinsics["near"]}
            P = truth["settings"]["near"]["pupil_magnification"]
            fits = {"thin (one setting)": fit(one), "thick, P given (one setting)": fit(one, pupil_magnification=P),
                    "thick (bracket, P fitted)": fit(table)}
            row = {"lens": name, "pupil_magnification": P, "seconds_render": t_render, "seconds_measure": t_measure,
                   "fits": {}}
            for how, res in fits.items():
                row["fits"][how] = {"errors": _errors(res, truth, "near"), "result": res.code,
                                    "pupil_magnification": res.pupil_magnification.value,
                                    "pupil_magnification_sigma": res.pupil_magnification.sigma}
            rows.append(row)
    return {"rows": rows, "samples_per_pixel": spp}
