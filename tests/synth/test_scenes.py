"""The example scenes in data_specs/scenes: each one either fits (and a test fits it) or says in
its header that it is a render-only example, and then `lensfit fit` does refuse its stack."""

from __future__ import annotations

import json

import pytest

from lensfit.cli import main
from lensfit.io.specs import specs_dir
from synth.rendering import render
from synth.scene import load_scene
from synth.stack import write_stack

SCENES = sorted(p.stem for p in (specs_dir() / "scenes").glob("*.toml"))
#: Scenes that fit, and where that is tested.
FITTED = {"demo": "tests/docs/test_docs.py (the README's example)", "printed_target": "docs/examples/real_camera.py", "focus_bracket": "tests/measurement/test_fit_pipeline.py",
          "bench_calibration": "tests/bench/test_bench.py (quick suite)", "camera_raw": "this file",
          "stopped_down": "tests/measurement/test_diffraction.py"}


def header(name: str) -> str:
    lines = (specs_dir() / "scenes" / f"{name}.toml").read_text().splitlines()
    return "\n".join(line for line in lines if line.startswith("#"))


def render_only() -> list[str]:
    return [n for n in SCENES if "Render-only example" in header(n)]


def test_every_example_scene_says_whether_it_fits():
    assert set(SCENES) == set(FITTED) | set(render_only()), "a new scene must fit (add it to FITTED) or say why not"
    assert not set(FITTED) & set(render_only())


@pytest.mark.parametrize("name", render_only())
def test_a_render_only_scene_is_refused_as_its_header_says(name, tmp_path, capsys):
    out = tmp_path / name
    write_stack(render(load_scene(specs_dir() / "scenes" / f"{name}.toml")), out)
    assert main(["fit", str(out)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_the_camera_raw_scene_fits(camera_raw_stack):
    out = camera_raw_stack
    from lensfit.fitting import fit
    from lensfit.measurement.measure import measure

    truth = json.loads((out / "truth.json").read_text())
    r = fit(measure(out))
    assert r.code == "ok"
    assert r.focal_length_mm.value == pytest.approx(truth["focal_length_mm"], rel=0.02)
    for label, t in truth["settings"].items():
        assert r.settings[label]["f_number"].value == pytest.approx(t["f_number"], rel=0.03)
        assert r.settings[label]["focus_distance_mm"].value == pytest.approx(t["focus_distance_mm"], rel=0.02)
