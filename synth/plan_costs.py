"""How good ``synth plan``'s time estimates are (``synth bench --plan-costs``): shipped scenes,
thin and compound lenses, one wavelength and several, each planned and then rendered (after a
warm-up render, so compilation is left out as the plan leaves it out), estimated against
measured seconds. Measured, never asserted in tests; the record is shown on the validation page.
"""

from __future__ import annotations

import time
import tomllib
from pathlib import Path
from typing import Any, Callable

from lensfit.io.specs import specs_dir

#: (what, shipped scene, changes as dotted keys): thin lenses, the four shipped designs (6-13
#: surfaces), more samples, several wavelengths.
CASES: list[tuple[str, str, dict[str, Any]]] = [
    ("demo: thin lens, 12 shots of 1 MP, 64 spp", "demo.toml", {}),
    ("colour: thin lens, RGB chromatic aberration", "colour.toml", {}),
    ("printed target: image texture, JPEG", "printed_target.toml", {}),
    ("Cooke triplet (6 surfaces), 16 spp", "compound_lens.toml", {}),
    ("telephoto (7 surfaces), 64 spp", "compound_lens.toml",
     {"lens.prescription": "telephoto-250", "render.samples_per_pixel": 64}),
    ("double Gauss (11 surfaces), 16 spp", "compound_lens.toml", {"lens.prescription": "double-gauss-50"}),
    ("retrofocus (13 surfaces), 3 wavelengths", "compound_lens.toml",
     {"lens.prescription": "retrofocus-24", "lens.wavelengths_nm": [486.1, 587.6, 656.3]}),
]
#: The plan promises its estimate within this factor of the measured time, either way.
WITHIN = 2.0


def scene_with(name: str, changes: dict[str, Any]):
    """The shipped scene ``name`` with ``changes`` (dotted keys) made to its TOML."""
    from synth.scene import scene_from_dict

    path = specs_dir() / "scenes" / name
    data = tomllib.loads(path.read_text())
    for key, value in changes.items():
        *parents, leaf = key.split(".")
        node = data
        for k in parents:
            node = node[k]
        node[leaf] = value
    return scene_from_dict(data, path)


def run(progress: Callable[[str], None] = lambda m: None) -> dict[str, Any]:
    """Every case: the plan's estimate and the measured seconds of a warm render."""
    import synth
    from synth.planning import plan

    rows = []
    for what, name, changes in CASES:
        progress(what)
        scene = scene_with(name, changes)
        plans = plan(scene)
        estimated = float(sum(p.estimated_s for p in plans))
        synth.render(scene)  # compilation, which the plan leaves out
        t0 = time.perf_counter()
        synth.render(scene)
        measured = time.perf_counter() - t0
        ratio = measured / estimated
        rows.append({"case": what, "scene": name, "changes": changes, "shots": len(plans),
                     "methods": sorted({p.method for p in plans}), "estimated_s": estimated, "measured_s": measured,
                     "ratio": ratio, "within": bool(1 / WITHIN <= ratio <= WITHIN)})
    from lensfit.bench.records import record_header

    return {**record_header("plan_costs", "synth bench --plan-costs"), "within_factor": WITHIN, "cases": rows,
            "passed": sum(r["within"] for r in rows), "total": len(rows)}


def markdown(doc: dict[str, Any]) -> str:
    """The record as the documentation's table."""
    out = [f"### synth plan's time estimates ({doc['passed']} of {doc['total']} within "
           f"{doc['within_factor']:g}x)", "",
           f"`{doc['command']}`, {doc['date']}, {doc['system']}, {doc['cores']} cores. Each scene planned, then "
           "rendered after a warm-up render (the plan's estimates leave compilation out).", "",
           "| scene | shots | method | estimated s | measured s | measured / estimated |", "|---|---|---|---|---|---|"]
    for r in doc["cases"]:
        out.append(f"| {r['case']} | {r['shots']} | {', '.join(r['methods'])} | {r['estimated_s']:.2f} | "
                   f"{r['measured_s']:.2f} | {r['ratio']:.2f}{'' if r['within'] else ' **outside**'} |")
    return "\n".join(out)


def record(doc: dict[str, Any], folder: str | Path) -> Path:
    """Write the record ``folder/plan_costs.json``."""
    from lensfit.bench.records import write_json

    return write_json(folder, "plan_costs", doc)
