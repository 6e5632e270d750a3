"""synth's files and command line: scene validation, the stack folder, atomic writes."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from lensfit.errors import SpecError
from lensfit.io.specs import specs_dir, validate
from synth import stack as stack_mod
from synth.cli import main
from synth.rendering import render
from synth.scene import load_scene

SMALL = """
[camera]
pixel_pitch_mm = 0.006
width_px = 96
height_px = 64

[lens]
focal_length_mm = 50.0
f_number = 4.0
focus_distance_mm = 1500.0

[render]
samples_per_pixel = 16

[[object]]
id = "board"
target = "checkerboard"
squares = [4, 3]
square_mm = 8.0
distance_mm = 1200.0

[[shot]]
setting = "a"

[[shot]]
setting = "a"
pose = [{ id = "board", distance_mm = 1800.0, tilt_deg = [0.0, 20.0] }]
"""


def write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_every_example_scene_is_valid():
    scenes = sorted((specs_dir() / "scenes").glob("*.toml"))
    assert any(p.name == "demo.toml" for p in scenes)
    for path in scenes:
        scene = load_scene(path)
        assert scene.shots


def test_demo_scene_is_a_calibration_stack():
    scene = load_scene(specs_dir() / "scenes" / "demo.toml")
    assert 10 <= len(scene.shots) <= 14
    D = scene.shots[0].camera.focus_distance_mm
    ratios = [o.pose.t_cam_target[2] / D for s in scene.shots for o in s.objects]
    assert min(ratios) == pytest.approx(0.5) and max(ratios) == pytest.approx(3.0)
    assert sum(not o.pose.fronto_parallel for s in scene.shots for o in s.objects) >= 2


@pytest.mark.parametrize(
    "old, new, field",
    [
        ("focal_length_mm = 50.0\n", "", "lens.focal_length_mm"),  # missing field
        ("distance_mm = 1200.0", "distance_mm = -5.0", "object[0].distance_mm"),  # negative distance
        ("focus_distance_mm = 1500.0", "focus_distance_mm = 30.0", "lens.focus_distance_mm"),  # inside f
        ('target = "checkerboard"', 'target = "teapot"', "object[0].target"),  # unknown target
        ("square_mm = 8.0\n", "", "object[0].square_mm"),  # target-specific field
        ('pose = [{ id = "board"', 'pose = [{ id = "bored"', "shot[1].pose[0].id"),
        ("distance_mm = 1800.0, tilt_deg = [0.0, 20.0]", "distance_mm = 60.0, tilt_deg = [0.0, 80.0]",
         "shot[1].pose.distance_mm"),  # a corner behind the focal plane
    ],
)
def test_bad_scene_one_line_naming_file_and_field(tmp_path, capsys, old, new, field):
    assert old in SMALL
    path = write(tmp_path, SMALL.replace(old, new, 1))
    code, out, err = run(capsys, "plan", path)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert str(path) in lines[0] and field in lines[0]


def test_inconsistent_setting_is_refused(tmp_path):
    path = write(tmp_path, SMALL.replace('[[shot]]\nsetting = "a"\npose', '[[shot]]\nsetting = "a"\nf_number = 8.0\npose'))
    with pytest.raises(SpecError, match=r"shot\[1\]\.setting"):
        load_scene(path)


def test_render_writes_a_complete_stack(tmp_path, capsys):
    scene = write(tmp_path, SMALL)
    out = tmp_path / "stack"
    code, stdout, err = run(capsys, "render", scene, "--out", out, "--seed", "3")
    assert code == 0, err
    manifest = tomllib.loads((out / "stack.toml").read_text())
    validate(manifest, "stack", out / "stack.toml")
    truth = json.loads((out / "truth.json").read_text())
    validate(truth, "truth", out / "truth.json")
    # The manifest holds only what a photographer knows: never the answer.
    text = (out / "stack.toml").read_text()
    for secret in ("focal_length", "f_number", "focus_distance", "coc"):
        assert secret not in text
    assert [i["file"] for i in manifest["image"]] == ["shot_000.png", "shot_001.png"]
    assert truth["settings"]["a"]["sensor_distance_mm"] == pytest.approx(1 / (1 / 50 - 1 / 1500))
    assert [i["method"] for i in truth["images"]] == ["convolve", "raytrace"]
    for entry in truth["images"]:
        img = cv2.imread(str(out / entry["file"]), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint16 and img.shape == (64, 96)
        maps = np.load(out / entry["maps"])
        assert maps["depth_mm"].shape == (64, 96)
        target = entry["targets"][0]
        # Per-edge CoC follows the formula at the edge's own distance (tilted: it varies).
        for edge in target["edges"]:
            for z, c in zip(edge["distance_mm"], edge["coc_diameter_px"]):
                s = truth["settings"]["a"]["sensor_distance_mm"]
                assert c == pytest.approx((50 / 4) * s * abs(1 / 1500 - 1 / z) / 0.006, rel=1e-9)
    tilted = truth["images"][1]["targets"][0]
    assert np.ptp([z for e in tilted["edges"] for z in e["distance_mm"]]) > 10
    # The 16-bit file is the quantised linear render.
    again = render(load_scene(scene), seed=3)
    np.testing.assert_array_equal(cv2.imread(str(out / "shot_001.png"), cv2.IMREAD_UNCHANGED),
                                  stack_mod.quantise_16bit(again.images["shot_001.png"]))


def test_render_refuses_non_empty_out_without_force(tmp_path, capsys):
    scene = write(tmp_path, SMALL)
    out = tmp_path / "stack"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    code, _, err = run(capsys, "render", scene, "--out", out)
    assert code == 2 and "--out" in err and "--force" in err
    assert (out / "precious.txt").read_text() == "keep me"
    code, _, err = run(capsys, "render", scene, "--out", out, "--force")  # --force replaces only synth's own stacks
    assert code == 2 and "did not write" in err and (out / "precious.txt").read_text() == "keep me"
    (out / "precious.txt").unlink()
    code, _, err = run(capsys, "render", scene, "--out", out)  # an empty folder is fine
    assert code == 0 and (out / "truth.json").exists()
    code, _, err = run(capsys, "render", scene, "--out", out, "--force", "--seed", "5")
    assert code == 0 and json.loads((out / "truth.json").read_text())["seed"] == 5


@pytest.mark.parametrize("writer", ["_write_image", "_write_maps"])
def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch, writer):
    # The images and truth maps are written by a few threads at once: one failed write stops
    # the stack as a whole, with no temporary sibling left behind.
    result = render(load_scene(write(tmp_path, SMALL)))
    calls = []

    def failing(path, *_):
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        Path(path).write_bytes(b"x")

    monkeypatch.setattr(stack_mod, writer, failing)
    with pytest.raises(OSError):
        stack_mod.write_stack(result, tmp_path / "stack")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]


def test_float_tiff_output(tmp_path, capsys):
    import tifffile

    scene = write(tmp_path, SMALL)
    code, _, err = run(capsys, "render", scene, "--out", tmp_path / "f", "--format", "float-tiff")
    assert code == 0, err
    img = tifffile.imread(tmp_path / "f" / "shot_000.tiff")
    assert img.dtype == np.float32
    np.testing.assert_allclose(img, render(load_scene(scene), image_format="float-tiff").images["shot_000.tiff"], atol=0)


def test_plan_lists_stages_method_and_cost(tmp_path, capsys):
    code, out, _ = run(capsys, "plan", write(tmp_path, SMALL))
    assert code == 0
    assert "convolve" in out and "raytrace" in out and "defocus" in out and "tilted" in out and "est" in out


def test_help_does_not_import_jax():
    import subprocess
    import sys

    code = ("import sys\nfrom synth.cli import main\ntry:\n    main(['render', '--help'])\n"
            "except SystemExit:\n    pass\nassert 'jax' not in sys.modules\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_preview_contact_sheet_is_the_render_in_srgb(tmp_path, capsys):
    """Every shot in the sheet, encoded with the sRGB curve: decoding it (lensfit's decoder)
    gives back the linear render on one exposure scale; an existing sheet needs --force."""
    from lensfit.io.images import srgb_to_linear

    scene = write(tmp_path, SMALL)
    out, sheet_path = tmp_path / "stack", tmp_path / "sheet.png"
    code, stdout, err = run(capsys, "render", scene, "--out", out, "--preview", sheet_path)
    assert code == 0, err
    sheet = cv2.imread(str(sheet_path), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64)
    assert sheet.shape == (64 + 2 * 4, 2 * 96 + 3 * 4, 3)  # 2 shots side by side, 4 px gaps
    truth = json.loads((out / "truth.json").read_text())
    linear = [cv2.imread(str(out / i["file"]), cv2.IMREAD_UNCHANGED) / 65535.0 for i in truth["images"]]
    white = np.percentile(np.concatenate([im.ravel() for im in linear]), 99.5)
    for k, im in enumerate(linear):
        tile = sheet[4:4 + 64, 4 + k * 100:4 + k * 100 + 96, 1]
        below_label = (slice(20, None), slice(None))  # the shot name is written top left
        decoded = srgb_to_linear(tile / 255.0) * white
        assert np.allclose(decoded[below_label], np.clip(im, 0, white)[below_label], atol=0.01)
    code, _, err = run(capsys, "render", scene, "--out", tmp_path / "other", "--preview", sheet_path)
    assert code == 2 and "--preview" in err and "--force" in err


@pytest.mark.parametrize("argv, says", [
    (["--spp", "0"], "--spp must be between 1 and 65536, got 0"),
    (["--pairs", "0"], "--pairs must be >= 1, got 0"),
    (["--scene", str(specs_dir() / "scenes" / "slanted_edges.toml")], "Mitsuba cannot render target 'edge-1200'"),
    (["--spp", "16", "70000"], "--spp must be between 1 and 65536, got 70000"),
    (["--scene", str(specs_dir() / "scenes" / "demo.toml"), "--record", "records"],
     "--scene must be given only without --record"),
])
def test_bench_against_mitsuba_refuses_bad_arguments_in_one_line(argv, says, capsys):
    # Refused before any process is started: exit 2 and one line naming the option and the value.
    assert main(["bench", "--against-mitsuba", "--pairs", "1", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err

