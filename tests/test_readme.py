"""The README's Python examples run as written (a user copies them first), and what they
compute is right: the render-then-fit round trip recovers the demo lens it rendered."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def python_blocks() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", (ROOT / "README.md").read_text(), flags=re.S | re.M)


def test_readme_python_examples_run_and_recover_the_rendered_lens(tmp_path, monkeypatch):
    blocks = python_blocks()
    assert len(blocks) >= 2
    render_block = next(b for b in blocks if "synth.render(" in b)
    fit_block = next(b for b in blocks if "lensfit.fit(" in b)
    (tmp_path / "data_specs").symlink_to(ROOT / "data_specs")
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(render_block, "README.md (Python API)", "exec"), scope)
    exec(compile(fit_block, "README.md (fit)", "exec"), scope)
    truth = json.loads(Path("out/demo/truth.json").read_text())
    result = scope["result"]
    assert result.code == "ok"
    N = result.settings["a"]["f_number"]
    assert N.value == pytest.approx(truth["settings"]["a"]["f_number"], rel=0.02)
    assert N.ci95[0] < N.value < N.ci95[1]
    assert result.focal_length_mm.value == pytest.approx(truth["focal_length_mm"], rel=0.02)
