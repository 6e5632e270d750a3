"""The documentation runs as written (a user copies it first), and what it computes is right.

- README.md is a short entry point (at most 200 lines) whose accuracy table is the one the
  benchmark records give.
- Every command line of the README and the docs pages (indented ``.venv/bin/lensfit ...`` /
  ``.venv/bin/synth ...``) is parsed by the program's own argument parser, with each
  ``[optional]`` group added in its first form: a documented option that does not exist, or takes
  another form, fails here. The commands that run in seconds run as written, on the stack the
  README's Python example renders; only the benchmarks (minutes to hours) are parsed, not run.
- The Python blocks run as written, in order, and the README's recovers the demo lens.
- ``make docs``'s build succeeds in strict mode (a warning fails), and its generated pages hold
  every subcommand and every schema.
- Every example in docs/examples/ runs, draws the figure its page shows, and the fitting ones
  recover the lens they rendered.
- No dated notes in lensfit/ or synth/: history belongs in CHANGELOG.md and git.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md", *sorted((DOCS / "src").rglob("*.md"))]
TEXTS = {p: p.read_text() for p in PAGES}
#: Placeholder words of the option lists -> a value of the right kind.
PLACEHOLDERS = {"MM": "0.005", "N": "2", "PX": "1.5", "MP": "50", "NAME": "full-frame", "FILE": "x.json",
                "PCT": "1", "HOST:PORT": "localhost:8786", "NM": "550", "DIR": "records"}
#: Commands that take minutes: parsed, not run here.
SLOW = ("bench", "bench-fit", "bench-lenses", "bench-measure", "bench-api", "bench-stages", "bench-hostile",
        "bench-developed")
EXAMPLES = sorted((DOCS / "examples").glob("*.py"))


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def python_blocks() -> list[tuple[str, str]]:
    """(page, code) of every Python block, the README's first."""
    return [(_rel(p), code) for p in PAGES for code in re.findall(r"^```python\n(.*?)^```", TEXTS[p], flags=re.S | re.M)]


def command_lines() -> list[tuple[str, str, str]]:
    """(page, program, rest of the line without its trailing comment) of every documented command."""
    out = []
    for p in PAGES:
        for program, rest in re.findall(r"^    \.venv/bin/(lensfit|synth) (.*)$", TEXTS[p], flags=re.M):
            out.append((_rel(p), program, re.split(r"\s{2,}#", rest)[0].strip()))
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


def test_readme_is_a_short_entry_point_linking_pages_that_exist():
    text = TEXTS[ROOT / "README.md"]
    assert len(text.splitlines()) <= 200
    assert "    make demo\n    make test\n" in text
    for link in re.findall(r"\]\(([^)#]+)\)", text):
        if not link.startswith("http"):
            assert (ROOT / link).is_file(), f"README links to a missing file: {link}"


def test_readme_accuracy_table_is_the_records():
    from lensfit.bench.records import END, START, headline_table, load_records

    records = load_records(DOCS / "validation" / "records")
    assert {r["suite"] for r in records} >= {"standard"}, "no benchmark record: run lensfit bench --record"
    text = TEXTS[ROOT / "README.md"]
    block = text[text.index(START) + len(START):text.index(END)].strip()
    assert block == headline_table(records).strip(), "README's table is stale: run make readme-table"
    for r in records:  # each says when and how it was made
        assert r["date"] and r["command"].startswith("lensfit bench") and r["cases"] > 0


def test_every_subcommand_is_shown_in_a_guide_or_the_readme():
    import argparse

    lines = command_lines()
    for program in ("lensfit", "synth"):
        parser = parser_for(program)
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        documented = {shlex.split(rest)[0] for _, prog, rest in lines if prog == program}
        assert set(sub.choices) <= documented, f"{program}: no example of {set(sub.choices) - documented}"


@pytest.mark.parametrize("page, program, line", command_lines(),
                         ids=lambda v: v if isinstance(v, str) and not v.endswith(".md") else None)
def test_every_documented_command_parses_with_each_option(page, program, line):
    parser = parser_for(program)
    required, groups = split(line)
    try:
        parser.parse_args(required)
        for g in groups:
            parser.parse_args(required + g)
    except SystemExit as exc:  # argparse's way of saying no
        pytest.fail(f"{page}: command does not parse: {program} {line} ({exc})")


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A working folder as the docs assume one (data_specs beside out/)."""
    work = tmp_path_factory.mktemp("docs")
    (work / "data_specs").symlink_to(ROOT / "data_specs")
    return work


def test_python_blocks_and_commands_run_as_written(work, monkeypatch, capsys):
    from lensfit.cli import main as lensfit_main
    from synth.cli import main as synth_main

    monkeypatch.chdir(work)
    blocks = python_blocks()
    assert blocks[0][0] == "README.md" and "synth.render(" in blocks[0][1]
    scope: dict = {}
    for page, code in blocks:
        exec(compile(code, f"{page} (Python block)", "exec"), scope)
        if page == "README.md":  # the README's example recovers the demo lens
            truth = json.loads(Path("out/api_demo/truth.json").read_text())
            result = scope["result"]
            assert result.code == "ok"
            N = result.settings["a"]["f_number"]
            assert N.value == pytest.approx(truth["settings"]["a"]["f_number"], rel=0.01)
            assert N.ci95[0] < truth["settings"]["a"]["f_number"] < N.ci95[1]
            assert result.focal_length_mm.value == pytest.approx(truth["focal_length_mm"], rel=0.01)
    capsys.readouterr()

    # photos for `lensfit init photos`: one JPEG as a camera writes it (EXIF: Canon EOS R5)
    from helpers import jpeg_with_exif

    Path("photos").mkdir()
    jpeg_with_exif(Path("photos/IMG_0001.jpg"))
    ran = set()
    for page, program, line in command_lines():
        required, _ = split(line)
        name = required[0]
        if name in SLOW or (program, name) == ("synth", "bench") or (program, name, required[1:2]) in (
                ("synth", "render", ["data_specs/scenes/demo.toml"]),):
            continue  # minutes; or the demo scene, which the README's Python example rendered
        if program == "lensfit" and name == "fit" and required[1] == "photos":
            continue  # one synthetic JPEG is no calibration stack; docs/examples/real_camera.py fits one
        if program == "lensfit" and name in ("fit", "measure") and required[1] == "out/demo":
            required = [a.replace("out/demo", "out/api_demo") for a in required]  # the stack rendered above
        if program == "lensfit" and name == "fit" and required[1] == "samples.json":
            assert lensfit_main(["measure", "out/api_demo", "--out", "samples.json", "--force"]) == 0
        if program == "lensfit" and name in ("target", "measure", "init"):  # several pages show them: each as if first
            writes = [required[i + 1] for i, a in enumerate(required[:-1]) if a in ("--out", "--entry")]
            for f in writes if name != "init" else ["photos/stack.toml"]:  # what this command writes
                Path(f).unlink(missing_ok=True)
        main = lensfit_main if program == "lensfit" else synth_main
        code = main(required)
        out = capsys.readouterr()
        assert code == 0, f"{page}: {program} {' '.join(required)} exited {code}: {out.err.strip()[-300:]}"
        ran.add((program, name))
        if (program, name) == ("lensfit", "fit"):
            assert "f_number" in out.out or "f-number" in out.out.lower()
    assert {("lensfit", "dof"), ("lensfit", "target"), ("lensfit", "plan"), ("lensfit", "init"),
            ("lensfit", "measure"), ("lensfit", "fit"), ("synth", "plan"), ("synth", "render")} <= ran
    assert Path("board.toml").is_file() and Path("photos/stack.toml").is_file()


def test_docs_build_strictly_with_every_command_and_schema(tmp_path):
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                          str(DOCS / "mkdocs.yml"), "--site-dir", str(site)], capture_output=True, text=True, env=env,
                         cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "WARNING" not in run.stderr, run.stderr[-3000:]
    cli = (site / "reference" / "cli" / "index.html").read_text()
    import argparse

    for program in ("lensfit", "synth"):
        sub = next(a for a in parser_for(program)._actions if isinstance(a, argparse._SubParsersAction))
        for name in sub.choices:
            assert f"{program} {name}" in cli, f"CLI reference lacks {program} {name}"
    formats = (site / "reference" / "formats" / "index.html").read_text()
    for schema in (ROOT / "data_specs" / "schemas").glob("*.schema.json"):
        assert schema.name in formats
    api = (site / "reference" / "api" / "index.html").read_text()
    assert "measure_and_fit" in api and "Examples" in api
    from lensfit.bench.records import load_records

    validation = (site / "validation" / "index.html").read_text()
    for record in load_records(DOCS / "validation" / "records"):
        assert f"Suite <code>{record['suite']}</code>" in validation
    if (DOCS / "validation" / "records" / "api_vs_cli.json").is_file():
        assert "The library against the command line" in validation
    for example in EXAMPLES:
        page = (site / "examples" / example.stem / "index.html").read_text()
        assert f"img/{example.stem}.png" in page, f"the page of {example.name} shows no figure"


@pytest.mark.slow
@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.stem)
def test_example_runs_and_draws_its_figure(example, tmp_path):
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, str(example), str(out)], capture_output=True, text=True, cwd=ROOT,
                         timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    figure = out / f"{example.stem}.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{example.name} drew no {figure.name}"
    assert (DOCS / "src" / "examples" / "img" / figure.name).is_file(), "the page's copy of the figure is missing"
    # the fitting examples print each estimate's error against the truth they rendered
    errors = [float(e) for e in re.findall(r"([+-]\d+\.\d+) %\)", run.stdout)]
    if example.stem in ("fit_report", "focus_bracket", "real_camera"):
        assert len(errors) >= 3 and max(abs(e) for e in errors) < 2.0, run.stdout


#: A dated note: an ISO date, or "until/before/since/tried" with a date, in a comment or docstring.
DATED = re.compile(r"\b20\d\d-\d\d-\d\d\b")
#: Dates that are names of things, not history (a catalogue's edition).
NOT_HISTORY = ("SCHOTT Zemax catalogue 2017-01-20b",)


def test_no_dated_notes_in_the_code():
    found = []
    for package in ("lensfit", "synth"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for n, line in enumerate(path.read_text().splitlines(), 1):
                if DATED.search(line) and not any(name in line for name in NOT_HISTORY):
                    found.append(f"{_rel(path)}:{n}: {line.strip()[:90]}")
    assert not found, "dated notes belong in CHANGELOG.md:\n" + "\n".join(found)


def test_changelog_keeps_a_changelog():
    text = (ROOT / "CHANGELOG.md").read_text()
    assert text.startswith("# Changelog") and "## [Unreleased]" in text
    assert re.search(r"^## \[\d+\.\d+\.\d+\] - \d{4}-\d\d-\d\d$", text, flags=re.M)
