"""Every field a user writes, driven with values of the wrong type, out of range and absurd.

The cases come from the published schemas (``data_specs/schemas``), not from the loaders: each
leaf field of a stack manifest, a scene and a benchmark suite is set, one at a time, in a file
that is otherwise valid, to a string where a number belongs, a boolean, a list, NaN, infinity,
a value past each bound the schema states, a wrong-length list, a name outside an enumeration.
Each must be refused with a ``SpecError`` that names the field as the file spells it
(``target[0].square_mm``), never accepted and never an internal error; and through the CLI
with exit status 2 and one line.
"""

from __future__ import annotations

import copy
import json
import math
import re
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from lensfit.errors import SpecError
from lensfit.io.specs import specs_dir

SCHEMAS = specs_dir() / "schemas"

STACK = {
    "camera": {"pixel_pitch_mm": 0.006, "sensor_width_mm": 36.0},
    "lens": {"pupil_magnification": 1.0, "focusing": "unit", "ideal": False},
    "target": [{"id": "board", "kind": "charuco", "squares": [6, 4], "square_mm": 30.0, "marker_mm": 22.0,
                "dictionary": "DICT_4X4_50"}],
    "image": [{"file": "a.png", "encoding": "linear", "setting": "a", "distance_mm": 1000.0, "black_level": 0,
               "white_level": 255, "rotate_deg": 0, "targets": ["board"]}],
    "intrinsics": [{"setting": "a", "focal_length_px": 5000.0, "focal_length_sigma_px": 5.0,
                    "principal_point_px": [48.0, 32.0], "distortion": [0.0, 0.0, 0.0, 0.0, 0.0]}],
}

def _scene() -> dict:
    """test_hostile's small scene, calling for every effect so that every effect's table is read."""
    from test_hostile import SCENE as SMALL

    scene = tomllib.loads(SMALL)
    scene["render"].update(effects=["defocus", "diffraction", "vignetting", "distortion", "chromatic_aberration",
                                    "exposure", "noise", "mosaic"], format="dng")
    scene.update(shot=[{"name": "s0", "pose": [{"id": "board"}]}], exposure={"shutter_s": 0.01},
                 diffraction={"reach_rings": 2}, vignetting={"natural": True}, distortion={"k1": 0.01},
                 chromatic_aberration={"focal_shift_mm": [0.0, 0.0, 0.0]}, noise={"shot": True},
                 mosaic={"pattern": "RGGB"}, sensor={"preset": "aps-c-24mp"})
    return scene


SUITE = """
name = "driven"
seeds = [0]
estimators = ["edge"]

[tolerances]
f_number = 0.02

[[scene]]
file = "bench_calibration.toml"

[[render]]
method = "raytrace"
samples_per_pixel = 8

[[noise]]
name = "none"
full_well_e = 2000.0
read_noise_e = 3.0
exposure = 0.5

[[solver]]
loss = "huber"
blur_floor_px = 0.5

[[effects]]
name = "camera-raw"
effects = ["defocus", "diffraction", "vignetting", "exposure", "mosaic", "noise"]
exposure = { shutter_s = 0.003, iso = 800, luminance_cd_m2 = 2000.0 }
sensor = { preset = "aps-c-24mp" }
"""


def _resolve(spec: dict, defs: dict) -> dict:
    while "$ref" in spec:
        spec = {**defs[spec["$ref"].split("/")[-1]], **{k: v for k, v in spec.items() if k != "$ref"}}
    return spec


def bad_values(spec: dict, defs: dict) -> list:
    """Values the schema says are wrong for a field: the wrong type, past each bound, absurd."""
    spec = _resolve(spec, defs)
    kind, out = spec.get("type"), []
    if "oneOf" in spec:  # a number or a word ("inf"): the number's wrongs
        if any(_resolve(s, defs).get("type") == "number" for s in spec["oneOf"]):
            out += ["abc", True, [1.0], math.nan, -math.inf, -1.0]
        return out
    if kind in ("number", "integer"):
        out += ["abc", True, [1.0], math.nan, math.inf, -math.inf]
        if kind == "integer":
            out.append(2.5)
        if "maximum" in spec:
            out.append(spec["maximum"] * 10 + 1)
        if "exclusiveMinimum" in spec:
            out.append(spec["exclusiveMinimum"])
        if "minimum" in spec:
            out.append(spec["minimum"] - 1)
    elif kind == "string":
        out += [3, [1], True]
    elif kind == "boolean":
        out += ["yes", 1]
    elif kind == "array":
        out += ["x", 5]
        if spec.get("minItems", 0) > 1:
            out.append([1.0] * (spec["minItems"] - 1))
        if "maxItems" in spec:
            out.append([1.0] * (spec["maxItems"] + 1))
        items = _resolve(spec.get("items", {}), defs)
        if items.get("type") in ("number", "integer"):
            k = max(spec.get("minItems", 1), 1)
            out += [["q"] * k, [math.nan] * k]
            if "maximum" in items:
                out.append([items["maximum"] * 10 + 1] * k)
    if "enum" in spec:
        out += ["nope", 7]
    return out


def leaves(spec: dict, defs: dict, path: tuple = ()) -> Iterator[tuple[tuple, dict]]:
    """Every leaf field of a schema, tables of tables entered at their first element."""
    spec = _resolve(spec, defs)
    if spec.get("type") == "object" and "properties" in spec:
        for key, sub in spec["properties"].items():
            yield from leaves(sub, defs, (*path, key))
    elif spec.get("type") == "array" and _resolve(spec.get("items", {}), defs).get("type") == "object":
        yield from leaves(spec["items"], defs, (*path, 0))
    else:
        yield path, spec


def field_name(path: tuple) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else ("." if out else "") + p
    return out


def with_value(base: dict, path: tuple, value) -> dict:
    data = copy.deepcopy(base)
    node = data
    for here, nxt in zip(path[:-1], path[1:], strict=True):
        if isinstance(here, int):
            while len(node) <= here:
                node.append({})
            node = node[here]
        else:
            node = node.setdefault(here, [] if isinstance(nxt, int) else {})
    node[path[-1]] = value
    return data


def cases(schema_name: str, base: dict) -> list[tuple[str, object, dict]]:
    schema = json.loads((SCHEMAS / schema_name).read_text())
    defs = schema.get("$defs", {})
    return [(field_name(path), value, with_value(base, path, value))
            for path, spec in leaves(schema, defs) for value in bad_values(spec, defs)]


def _toml(data: dict) -> str:
    return tomli_w.dumps(data)


def refusals(load, kind: str, base: dict) -> tuple[int, list[str]]:
    """Loads ``base`` (which must load) and then every bad case; what went wrong, as lines."""
    load(base)
    wrong = []
    found = cases(kind, base)
    for field, value, data in found:
        try:
            load(data)
            wrong.append(f"{field} = {value!r}: accepted")
        except SpecError as exc:
            if not re.search(re.escape(field) + r"(\[\d+\])?:", str(exc)):  # (an element: squares[1])
                wrong.append(f"{field} = {value!r}: refused without naming the field: {exc}")
        except Exception as exc:  # noqa: BLE001 (an internal error is what the test looks for)
            wrong.append(f"{field} = {value!r}: {type(exc).__name__}: {exc}")
    return len(found), wrong


@pytest.fixture()
def stack_folder(tmp_path: Path) -> Path:
    from PIL import Image

    folder = tmp_path / "stack"
    folder.mkdir()
    pixels = (np.random.default_rng(0).random((64, 96)) * 255).astype(np.uint8)
    Image.fromarray(pixels).save(folder / "a.png")
    return folder


def test_every_stack_toml_field(stack_folder: Path):
    from lensfit.io.stack import load_stack

    def load(data):
        (stack_folder / "stack.toml").write_text(_toml(data))
        load_stack(stack_folder)

    n, wrong = refusals(load, "stack.schema.json", STACK)
    assert n > 100 and not wrong, "\n".join(wrong)


def test_every_scene_field():
    from synth.scene import scene_from_dict

    n, wrong = refusals(scene_from_dict, "scene.schema.json", _scene())
    assert n > 400 and not wrong, "\n".join(wrong)


def test_every_bench_suite_field(tmp_path: Path):
    from lensfit.bench.suites import load_suite

    path = tmp_path / "driven.toml"

    def load(data):
        path.write_text(_toml(data))
        load_suite(path)

    n, wrong = refusals(load, "bench.schema.json", tomllib.loads(SUITE))
    assert n > 40 and not wrong, "\n".join(wrong)


def samples_rows() -> list[dict[str, str]]:
    """A samples CSV as lensfit measure writes it, every column filled, written out here: a V of
    blur against distance (thin lens, f 50 mm, f/4, focus 1500 mm, pitch 6 um)."""
    f, n, focus, pitch = 50.0, 4.0, 1500.0, 0.006
    rows = []
    for i, d in enumerate(np.linspace(700.0, 4000.0, 12).tolist()):
        c = (f / n) * (f * focus / (focus - f)) * abs(1 / d - 1 / focus) / pitch
        rows.append({"image": f"shot_{i}.png", "setting": "a", "target": "board", "edge": f"h{i}",
                     "distance_mm": f"{d!r}", "coc_diameter_px": f"{c!r}", "sigma_px": "0.05", "estimator": "edge",
                     "flags": "", "distance_start_mm": f"{d - 1!r}", "distance_end_mm": f"{d + 1!r}",
                     "start_px": "10.0 20.0", "end_px": "60.0 20.0", "distance_source": "pose",
                     "field_radius_px": "120.5", "disk_diameter_px": f"{c!r}", "disk_sigma_px": "0.05",
                     "pixel_pitch_mm": f"{pitch!r}", "focal_length_px": "8500.0", "focal_length_sigma_px": "4.0",
                     "distortion_k1": "0.01", "distortion_k2": "-0.002"})
    return rows


#: Numeric columns of a samples CSV and their wrong values (a field that may be negative, such
#: as a distortion coefficient, is not given -1).
SAMPLE_COLUMNS = {
    "distance_mm": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "coc_diameter_px": ("abc", "nan", "inf", "-1", "1e308"),
    "sigma_px": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "distance_start_mm": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "distance_end_mm": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "start_px": ("abc", "nan nan", "1 2 3", "inf 0", "1e308 1"),
    "end_px": ("abc", "nan nan", "1", "1e308 1"),
    "field_radius_px": ("abc", "nan", "inf", "-1", "1e308"),
    "disk_diameter_px": ("abc", "nan", "inf", "-1", "1e308"),
    "disk_sigma_px": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "pixel_pitch_mm": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "focal_length_px": ("abc", "nan", "inf", "-1", "0", "1e308"),
    "focal_length_sigma_px": ("abc", "nan", "inf", "-1", "1e308"),
    "distortion_k1": ("abc", "nan", "inf", "1e308"),
    "distortion_k2": ("abc", "nan", "inf", "1e308"),
}


def test_every_samples_csv_column(tmp_path: Path):
    """Each numeric column of a samples CSV, wrong on one row (every row, where a column is a
    setting's calibration that the rows repeat): refused naming the column, before any fitting."""
    import csv

    from lensfit.errors import InputError
    from lensfit.fitting.data import prepare
    from lensfit.io.samples import SampleTable

    path = tmp_path / "s.csv"
    base = samples_rows()

    def write(rows):
        with path.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)

    write(base)
    prepare(SampleTable.read(path))
    wrong = []
    for column, values in SAMPLE_COLUMNS.items():
        for value in values:
            for which in ([3], range(len(base))):
                rows = [dict(r) for r in base]
                for i in which:
                    rows[i][column] = value
                write(rows)
                try:
                    prepare(SampleTable.read(path))
                    wrong.append(f"{column} = {value!r} on rows {list(which)}: accepted")
                except (SpecError, InputError) as exc:
                    if column not in str(exc):
                        wrong.append(f"{column} = {value!r}: refused without naming the column: {exc}")
                except Exception as exc:  # noqa: BLE001 (an internal error is what the test looks for)
                    wrong.append(f"{column} = {value!r}: {type(exc).__name__}: {exc}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("command,kind", [("fit", "stack"), ("plan", "scene"), ("bench", "suite")])
def test_a_driven_field_through_the_cli_is_one_line_and_exit_2(tmp_path, stack_folder, capsys, command, kind):
    """One bad field per file kind through the command a user runs: exit 2, one line, the field named."""
    from test_hostile import one_line_error, run_cli

    from lensfit.cli import main as lensfit_main
    from synth.cli import main as synth_main

    if kind == "stack":
        (stack_folder / "stack.toml").write_text(_toml(with_value(STACK, ("target", 0, "square_mm"), -3.0)))
        code, _, err = run_cli(capsys, lensfit_main, "fit", stack_folder, "--out", tmp_path / "r.json")
        field = "target[0].square_mm"
    elif kind == "scene":
        scene = tmp_path / "scene.toml"
        scene.write_text(_toml(with_value(_scene(), ("distortion", "k2"), math.inf)))
        code, _, err = run_cli(capsys, synth_main, "plan", scene)
        field = "distortion.k2"
    else:
        suite = tmp_path / "driven.toml"
        suite.write_text(_toml(with_value(tomllib.loads(SUITE), ("noise", 0, "exposure"), 7.0)))
        code, _, err = run_cli(capsys, lensfit_main, "bench", "--suite", suite, "--out", tmp_path / "b")
        field = "noise[0].exposure"
    assert code == 2
    one_line_error(err, field)
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "b").exists()
