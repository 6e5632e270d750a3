"""The README runs as written (a user copies it first), and what it computes is right.

- Every command line of the README (indented ``.venv/bin/lensfit ...`` / ``.venv/bin/synth ...``)
  is parsed by the program's own argument parser, with each ``[optional]`` group added in its
  first form: a documented option that does not exist, or takes another form, fails here.
- The commands that run in seconds run as written; the demo chain (render, measure, fit, refit
  from samples) runs on the stack the README's Python example renders, and recovers the lens.
- The Python examples run as written: render-then-fit recovers the demo lens.
Only the benchmark commands (minutes to hours) are parsed and not run; tests/test_bench.py runs
a suite.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
#: Placeholder words of the README's option lists -> a value of the right kind.
PLACEHOLDERS = {"MM": "0.005", "N": "2", "PX": "1.5", "MP": "50", "NAME": "full-frame", "FILE": "x.json",
                "PCT": "1", "HOST:PORT": "localhost:8786", "NM": "550"}
#: Commands that take minutes: parsed, not run here.
SLOW = ("bench", "bench-fit", "bench-lenses", "bench-measure")


def python_blocks() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", README, flags=re.S | re.M)


def command_lines() -> list[tuple[str, str]]:
    """(program, rest of the line without its trailing comment) of every README command."""
    out = []
    for program, rest in re.findall(r"^    \.venv/bin/(lensfit|synth) (.*)$", README, flags=re.M):
        out.append((program, re.split(r"\s{2,}#", rest)[0].strip()))
    return out


def split(line: str) -> tuple[list[str], list[list[str]]]:
    """The required tokens and each [optional group] in its first form, placeholders filled."""
    groups = [g.split("|")[0].split() for g in re.findall(r"\[([^\]]*)\]", line)]
    required = shlex.split(re.sub(r"\[[^\]]*\]", " ", line))

    def fill(tokens):
        return [PLACEHOLDERS.get(t, t) for t in tokens]

    return fill(required), [fill(g) for g in groups]


def parser_for(program: str):
    if program == "lensfit":
        from lensfit.cli import build_parser
    else:
        from synth.cli import build_parser
    return build_parser()


def test_readme_lists_every_subcommand():
    import argparse

    for program in ("lensfit", "synth"):
        parser = parser_for(program)
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        documented = {shlex.split(rest)[0] for prog, rest in command_lines() if prog == program}
        assert set(sub.choices) <= documented, f"{program}: undocumented {set(sub.choices) - documented}"


@pytest.mark.parametrize("program, line", command_lines(), ids=lambda v: v if isinstance(v, str) else None)
def test_every_readme_command_parses_with_each_documented_option(program, line):
    parser = parser_for(program)
    required, groups = split(line)
    try:
        parser.parse_args(required)
        for g in groups:
            parser.parse_args(required + g)
    except SystemExit as exc:  # argparse's way of saying no
        pytest.fail(f"README command does not parse: {program} {line} ({exc})")


@pytest.fixture(scope="module")
def readme_dir(tmp_path_factory):
    """A working folder as the README assumes one (data_specs beside out/), with out/demo rendered
    by the README's own Python example."""
    work = tmp_path_factory.mktemp("readme")
    (work / "data_specs").symlink_to(ROOT / "data_specs")
    return work


def _run_python_blocks(work: Path, monkeypatch) -> dict:
    monkeypatch.chdir(work)
    scope: dict = {}
    blocks = python_blocks()
    assert len(blocks) >= 2
    render_block = next(b for b in blocks if "synth.render(" in b)
    fit_block = next(b for b in blocks if "lensfit.fit(" in b)
    exec(compile(render_block, "README.md (Python API)", "exec"), scope)
    exec(compile(fit_block, "README.md (fit)", "exec"), scope)
    return scope


def test_readme_python_examples_and_commands_run(readme_dir, monkeypatch, capsys):
    from lensfit.cli import main as lensfit_main
    from synth.cli import main as synth_main

    scope = _run_python_blocks(readme_dir, monkeypatch)
    truth = json.loads(Path("out/demo/truth.json").read_text())
    result = scope["result"]
    assert result.code == "ok"
    N = result.settings["a"]["f_number"]
    assert N.value == pytest.approx(truth["settings"]["a"]["f_number"], rel=0.02)
    assert N.ci95[0] < N.value < N.ci95[1]
    assert result.focal_length_mm.value == pytest.approx(truth["focal_length_mm"], rel=0.02)

    # photos for `lensfit init photos`: one JPEG as a camera writes it (EXIF: Canon EOS R5)
    from tests.test_init import jpeg_with_exif

    Path("photos").mkdir()
    jpeg_with_exif(Path("photos/IMG_0001.jpg"))
    ran = set()
    for program, line in command_lines():
        required, _ = split(line)
        name = required[0]
        if name in SLOW or (program, name) == ("synth", "bench"):
            continue
        if program == "synth" and name == "render":
            continue  # the Python example above rendered the same scene into out/demo
        if program == "lensfit" and name == "fit" and required[1] == "photos":
            continue  # one synthetic JPEG is no calibration stack; tests/test_init.py fits real round trips
        if program == "lensfit" and name == "fit" and required[1] == "samples.json":
            assert lensfit_main(["measure", "out/demo", "--out", "samples.json"]) == 0
        if program == "lensfit" and name == "target":  # two sections print the board: each as if first
            for f in ("board.pdf", "board.toml"):
                Path(f).unlink(missing_ok=True)
        main = lensfit_main if program == "lensfit" else synth_main
        code = main(required)
        out = capsys.readouterr()
        assert code == 0, f"{program} {' '.join(required)} exited {code}: {out.err.strip()[-300:]}"
        ran.add((program, name))
        if (program, name) == ("lensfit", "fit"):  # the README's fit of the demo stack recovers it
            assert "f_number" in out.out and "error" not in out.err.lower()
    assert {("lensfit", "dof"), ("lensfit", "target"), ("lensfit", "plan"), ("lensfit", "init"),
            ("lensfit", "measure"), ("lensfit", "fit"), ("synth", "plan")} <= ran
    assert Path("board.toml").is_file() and Path("photos/stack.toml").is_file()
