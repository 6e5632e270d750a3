"""render -> measure -> fit, judged against the truth the stacks were rendered from; the
``lensfit fit`` command line (exit codes, files, refusals)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import re

import imageio.v3 as iio
import jsonschema
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers import assert_recovered_or_refused
from lensfit.fitting import fit
from lensfit.measurement.measure import SampleTable, measure
from lensfit.io.specs import schema
from synth.rendering import render
from synth.scene import scene_from_dict
from synth.stack import write_stack


def within(est, truth, rel, k_sigma=4.0):
    assert est.value is not None, est.reason
    assert abs(est.value / truth - 1) <= rel, (est.value, truth)
    assert abs(est.value - truth) <= k_sigma * est.sigma, (est.value, truth, est.sigma)


def test_fit_of_a_rendered_calibration_stack(calibration_stack, calibration_samples):
    truth = json.loads((calibration_stack / "truth.json").read_text())
    r = fit(calibration_samples)
    assert r.ok, r.reasons
    est = r.settings["a"]
    t = truth["settings"]["a"]
    within(est["focal_length_mm"], truth["focal_length_mm"], 0.003)
    within(est["f_number"], t["f_number"], 0.005)
    within(est["focus_distance_mm"], t["focus_distance_mm"], 0.005)
    within(est["sensor_distance_mm"], t["sensor_distance_mm"], 0.003)
    assert r.chi2_reduced < 5  # the model describes the measured blur


def test_fit_cli_writes_results_plot_and_compares_with_truth(calibration_stack, tmp_path, capsys):
    from lensfit.cli import main

    samples = tmp_path / "samples.json"
    truth_copy = tmp_path / "stack"
    out, plot = tmp_path / "results.json", tmp_path / "fit.png"
    # From the stack folder (measure + fit), with the truth beside it; the samples as fitted
    # (with the diffraction test's verdict on them).
    assert main(["fit", str(calibration_stack), "--out", str(out), "--plot", str(plot), "--samples", str(samples)]) == 0
    text = capsys.readouterr().out
    assert "truth" in text and "focal_length_mm" in text and "%" in text
    doc = json.loads(out.read_text())
    jsonschema.validate(doc, schema("results"))
    truth = json.loads((calibration_stack / "truth.json").read_text())
    assert doc["settings"]["a"]["f_number"]["value"] == pytest.approx(truth["settings"]["a"]["f_number"], rel=0.005)
    rows = {r["quantity"]: r for r in doc["truth_comparison"]}
    assert rows["f_number"]["truth"] == truth["settings"]["a"]["f_number"]
    assert abs(rows["focus_distance_mm"]["relative_error"]) < 0.005
    # the geometric calibration the fit used is reported beside it
    cal = doc["calibration"]["a"]
    assert cal["focal_length_px"] == pytest.approx(truth["settings"]["a"]["focal_length_px"], rel=0.005)
    assert cal["source"] == "calibrated" and len(cal["distortion_opencv"]) == 5
    img = iio.imread(plot)
    assert img.ndim == 3 and img.shape[0] > 300 and img.std() > 10  # a picture, not a blank
    # Outputs are not overwritten without --force, and stay as they were.
    before = out.read_text()
    assert main(["fit", str(samples), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err and out.read_text() == before
    # From a samples file (no truth): the same estimates.
    assert main(["fit", str(samples), "--out", str(out), "--force", "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["settings"]["a"]["f_number"]["value"] == pytest.approx(doc["settings"]["a"]["f_number"]["value"],
                                                                        rel=1e-6)
    assert "truth_comparison" not in again
    assert not truth_copy.exists()


def test_fit_cli_not_identifiable_has_its_own_exit_code(calibration_samples, tmp_path, capsys):
    """One distance only: the results file is still written, with the reason; exit 3."""
    from lensfit.cli import main

    one = SampleTable(pixel_pitch_mm=calibration_samples.pixel_pitch_mm, intrinsics=calibration_samples.intrinsics)
    by_image: dict[str, list] = {}
    for s in calibration_samples.samples:
        by_image.setdefault(s.image, []).append(s)

    def spread(samples):
        d = [s.distance_mm for s in samples]
        return (max(d) - min(d)) / min(d)

    one.samples = min(by_image.values(), key=spread)  # a fronto-parallel shot
    assert spread(one.samples) < 0.01
    assert len(one.samples) > 10
    samples, out = tmp_path / "one.json", tmp_path / "r.json"
    one.write(samples)
    assert main(["fit", str(samples), "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "not identifiable" in err and "one distance" in err
    doc = json.loads(out.read_text())
    jsonschema.validate(doc, schema("results"))
    assert doc["result"] == "not_identifiable"
    assert doc["settings"]["a"]["f_number"]["value"] is None
    assert "distances" in doc["settings"]["a"]["f_number"]["reason"]


def test_fit_cli_bad_input_is_one_line_naming_it(tmp_path, capsys):
    from lensfit.cli import main

    assert main(["fit", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing" in err
    bad = tmp_path / "bad.csv"
    bad.write_text("setting,distance_mm,coc_diameter_px,sigma_px\na,1000,x,0.1\n")
    assert main(["fit", str(bad), "--pixel-pitch", "0.006"]) == 2
    err = capsys.readouterr().err.strip()
    assert "bad.csv" in err and "coc_diameter_px" in err and "'x'" in err
    good = tmp_path / "good.csv"
    good.write_text("setting,distance_mm,coc_diameter_px,sigma_px\na,1000,3,0.1\n")
    assert main(["fit", str(good)]) == 2
    assert "--pixel-pitch" in capsys.readouterr().err
    assert main(["fit", str(good), "--pixel-pitch", "0.006", "--plot", str(tmp_path / "p.gif")]) == 2
    assert "--plot" in capsys.readouterr().err


def test_help_does_not_wait_for_jax():
    code = ("import sys\nfrom lensfit.cli import main\n"
            "try:\n    main(['fit', '--help'])\nexcept SystemExit:\n    pass\n"
            "assert 'jax' not in sys.modules and 'cv2' not in sys.modules, 'heavy import'\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "--plot" in done.stdout and "exit status" in done.stdout.lower()


# --------------------------------------------------------------------------- property, rendered


def slanted_square_stack(out, f, N, D, distances, c_max, seed=0):
    """A rendered stack: one slanted-edge square per image at each distance (fronto-parallel),
    the pixel pitch chosen so that the largest blur is ``c_max`` px, the square about 170 px at
    the nearest distance; intrinsics in stack.toml (as from an earlier calibration)."""
    inv_D = 0.0 if math.isinf(D) else 1.0 / D
    s = f if math.isinf(D) else f * D / (D - f)
    distances = np.asarray(distances, float)
    pitch = (f / N) * s * np.max(np.abs(inv_D - 1 / distances)) / c_max
    edge_mm = 170 * pitch * distances.min() / s
    shots = [{"pose": [{"id": "sq", "distance_mm": float(d), "tilt_deg": [0.0, 0.0]}]} for d in distances]
    scene = scene_from_dict({
        "camera": {"pixel_pitch_mm": float(pitch), "width_px": 420, "height_px": 320},
        "lens": {"focal_length_mm": float(f), "f_number": float(N), "focus_distance_mm": "inf" if math.isinf(D)
                 else float(D)},
        "render": {"samples_per_pixel": 64, "seed": int(seed), "method": "raytrace"},
        "background": {"value": 0.25},
        "object": [{"id": "sq", "target": "slanted-edge", "distance_mm": float(distances[0]), "edge_mm": float(edge_mm),
                    "size_mm": [float(2.4 * edge_mm), float(2.4 * edge_mm)], "angle_deg": 5.0}],
        "shot": shots,
    })
    result = render(scene)
    write_stack(result, out)
    f_px = result.truth["settings"]["a"]["focal_length_px"]
    manifest = out / "stack.toml"
    manifest.write_text(manifest.read_text() + f'\n[[intrinsics]]\nsetting = "a"\nfocal_length_px = {f_px}\n')
    return out


@pytest.mark.parametrize("case", ["focus at infinity", "macro 1:1", "target at the focus plane"])
def test_hard_cases_rendered(tmp_path, case):
    """render -> measure -> fit for hard captures: the truth within 3 %, or a typed refusal."""
    f, N, D, distances = {
        "focus at infinity": (50.0, 2.8, math.inf, [1500.0, 2000.0, 3000.0, 5000.0, 9000.0]),
        "macro 1:1": (60.0, 8.0, 120.0, [108.0, 113.0, 127.0, 134.0, 140.0]),
        "target at the focus plane": (35.0, 4.0, 1000.0, [700.0, 850.0, 1000.0, 1300.0, 1800.0]),
    }[case]
    r = fit(measure(slanted_square_stack(tmp_path / "stack", f, N, D, distances, c_max=12.0)))
    json.dumps(r.to_json_dict(), allow_nan=False)
    est = r.settings["a"]
    assert r.ok, r.reasons
    assert abs(est["focal_length_mm"].value / f - 1) < 0.01
    assert abs(est["f_number"].value / N - 1) < 0.03
    if math.isinf(D):
        inv = est["inverse_focus_distance_per_m"]
        assert abs(inv.value) < max(3 * inv.sigma, 0.01)  # within 1/100 m^-1 of infinity
        assert est["focus_distance_mm"].infinite or est["focus_distance_mm"].ci95[1] is None \
            or est["focus_distance_mm"].value > 50 * f
    else:
        assert abs(est["focus_distance_mm"].value / D - 1) < 0.01


def test_focus_bracket_scene_fits_jointly(tmp_path, monkeypatch):
    """The example focus bracket (two focus settings, shared focal length) end to end. Its
    settings have five views each, too few for the jackknife: each focal length's sigma is read
    through the covariance of the corners refined from the measured edge lines (which the
    measurement must carry to the calibration), and holds the truth within 3 of them."""
    import lensfit.calibration.camera as calibration
    from lensfit.io.specs import specs_dir
    from synth.scene import load_scene

    through_lines = []
    plain = calibration.correlated_sigma

    def recorded(*args, **kwargs):
        through_lines.append(plain(*args, **kwargs))
        return through_lines[-1]

    monkeypatch.setattr(calibration, "correlated_sigma", recorded)
    out = tmp_path / "fb"
    write_stack(render(load_scene(specs_dir() / "scenes" / "focus_bracket.toml")), out)
    truth = json.loads((out / "truth.json").read_text())
    table = measure(out)
    assert len(through_lines) == 2 and None not in through_lines, through_lines
    for label, intr in table.intrinsics.items():
        assert intr.focal_length_sigma_px in through_lines and intr.focal_length_sigma_method == "corner covariance"
        assert abs(intr.focal_length_px - truth["settings"][label]["focal_length_px"]) < 3 * intr.focal_length_sigma_px
    r = fit(table)
    assert r.ok, r.reasons
    assert set(r.settings) == {"near", "far"}
    within(r.focal_length_mm, truth["focal_length_mm"], 0.002)
    for label, t in truth["settings"].items():
        within(r.settings[label]["f_number"], t["f_number"], 0.005)
        within(r.settings[label]["focus_distance_mm"], t["focus_distance_mm"], 0.003)


def test_a_setting_its_views_cannot_calibrate_is_left_out_and_the_others_fitted(tmp_path, capsys):
    """The focus bracket with only two views of its near setting (a calibration needs three): the
    far setting is fitted and holds its truth; the near one is refused by name, with the fix, in
    the results (valid against the schema, no samples) and the exit status, not the whole stack
    (a bracket of a fast lens, whose nearest views were too blurred to find the board, had been
    refused entirely)."""
    from lensfit.cli import main
    from lensfit.io.specs import load_toml, specs_dir
    from lensfit.measurement.pipeline import measure_and_fit

    spec = load_toml(specs_dir() / "scenes" / "focus_bracket.toml")
    near = [k for k, shot in enumerate(spec["shot"]) if shot["setting"] == "near"]
    spec["shot"] = [shot for k, shot in enumerate(spec["shot"]) if k not in near[2:]]
    out = tmp_path / "fb"
    write_stack(render(scene_from_dict(spec)), out)
    truth = json.loads((out / "truth.json").read_text())
    table, r, _ = measure_and_fit(out)
    assert set(table.left_out_settings) == {"near"} and {s.setting for s in table.samples} == {"far"}
    assert r.code == "not_identifiable" and any("'near'" in why and "add views" in why for why in r.reasons)
    assert all(e.value is None and "left out" in e.reason for e in r.settings["near"].values())
    t = truth["settings"]["far"]
    for q in ("f_number", "focus_distance_mm"):
        within(r.settings["far"][q], t[q], 0.01)
    code = main(["fit", str(out), "--out", str(tmp_path / "r.json"), "--report", str(tmp_path / "r.html"), "--force"])
    assert code == 3 and "setting 'near' left out" in capsys.readouterr().err
    assert "its setting left out" in (tmp_path / "r.html").read_text()
    doc = json.loads((tmp_path / "r.json").read_text())
    jsonschema.validate(doc, schema("results"))
    assert doc["settings"]["near"]["samples"] == 0 and doc["settings"]["near"]["f_number"]["value"] is None
    # The Python API's fit of the table, and of the samples JSON written from it, say so too.
    table.write(tmp_path / "samples.json")
    for again in (fit(table), fit(SampleTable.read(tmp_path / "samples.json"))):
        assert again.code == "not_identifiable" and all(e.value is None for e in again.settings["near"].values())
        assert sum("'near'" in why for why in again.reasons) == 1
        within(again.settings["far"]["focus_distance_mm"], t["focus_distance_mm"], 0.01)


@settings(max_examples=4, deadline=None, derandomize=True, print_blob=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture])
@given(f=st.floats(15.0, 100.0), N=st.floats(1.4, 16.0), D_over_f=st.floats(15.0, 80.0),
       c_max=st.floats(4.0, 24.0), seed=st.integers(0, 1000))
def test_property_fit_of_render_recovers_the_lens(tmp_path_factory, f, N, D_over_f, c_max, seed):
    """fit(measure(render(theta))) recovers theta, for random lenses and one slanted-edge square
    per image at five distances on both sides of focus (intrinsics known, as from an earlier
    calibration)."""
    D = f * D_over_f
    out = tmp_path_factory.mktemp("prop") / "stack"
    r = fit(measure(slanted_square_stack(out, f, N, D, D * np.array([0.7, 0.85, 1.25, 1.7, 2.3]), c_max, seed)))
    # Ray-traced 64-spp stacks of 20 short edges: the blur estimates carry about 1-2 % of
    # systematic error here (see README), so 3 %; the sample-level tests check tighter.
    assert_recovered_or_refused(r, {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D}, 0.03)


@pytest.mark.parametrize("suffix", [".json", ".csv"])
def test_refit_from_a_samples_file_equals_the_fit_from_the_stack(calibration_samples, tmp_path, capsys, suffix):
    """Measure-then-refit: the samples file carries the calibration (and its sigma), and the JSON
    what the stack's [lens] says, so the fit from it has the stack fit's values and sigmas,
    through the API and the CLI (a CSV's user gives the lens's P)."""
    from lensfit.cli import main

    path = tmp_path / f"samples{suffix}"
    calibration_samples.write(path)
    lens = [] if suffix == ".json" else ["--pupil-magnification", "1", "--ideal-lens"]
    direct = fit(calibration_samples)
    again = fit(SampleTable.read(path), pupil_magnification=1.0 if lens else None, ideal_lens=True if lens else None)
    if suffix == ".json":  # the JSON keeps the calibration itself, with how its sigma was found
        assert SampleTable.read(path).intrinsics["a"] == calibration_samples.intrinsics["a"]
        assert calibration_samples.intrinsics["a"].focal_length_sigma_method == "jackknife"  # 8 views
    for q in ("focal_length_mm", "f_number", "focus_distance_mm"):
        a = getattr(direct, q) if q == "focal_length_mm" else direct.settings["a"][q]
        b = getattr(again, q) if q == "focal_length_mm" else again.settings["a"][q]
        assert b.value == pytest.approx(a.value, rel=1e-9) and b.sigma == pytest.approx(a.sigma, rel=1e-6), q
    assert main(["fit", str(path), "--json", *lens]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["focal_length_mm"]["sigma"] == pytest.approx(direct.focal_length_mm.sigma, rel=1e-6)


def test_a_non_finite_number_in_a_samples_csv_is_refused(calibration_samples, tmp_path):
    path = tmp_path / "samples.csv"
    calibration_samples.write(path)
    lines = path.read_text().splitlines()
    cells = lines[1].split(",")
    cells[5] = "nan"  # coc_diameter_px
    path.write_text("\n".join([lines[0], ",".join(cells), *lines[2:]]) + "\n")
    with pytest.raises(Exception, match=re.escape("line 2: coc_diameter_px")):
        SampleTable.read(path)


def test_measure_and_fit_are_reproducible(calibration_stack, calibration_samples):
    """The same stack gives the same samples and fit, bit for bit (OpenCV's multithreaded
    calibration once made them differ by up to 0.4 px near focus)."""
    again = measure(calibration_stack)
    assert [s.coc_diameter_px for s in again.samples] == [s.coc_diameter_px for s in calibration_samples.samples]
    assert [s.distance_mm for s in again.samples] == [s.distance_mm for s in calibration_samples.samples]
    a, b = fit(again), fit(calibration_samples)
    assert np.array_equal(a.parameters, b.parameters)


def test_blur_of_an_edge_across_depth_is_the_power_mean_the_model_uses(tmp_path):
    """Squares tilted 40-65 degrees near focus: the blur along their edges varies from 0 to 8 px.
    The edge estimator's single diameter is checked against power means of the local
    thin-lens CoC (the textbook formula, sampled densely here): the model's exponent (1.3) must
    fit within 10 % and beat both the mean (1) and the RMS (2) on average over the 24 edges
    (measured: 3.5 %, against 3.8 % and 10.3 %; the first four shots alone, 8 edges, the test's
    scene until 2026-11-28, are too few to tell 1.3 from the mean)."""
    from lensfit.fitting import BLUR_POWER_MEAN

    f, N, D, pitch = 50.0, 2.0, 1000.0, 0.01
    poses = [(1000.0, 55.0), (1000.0, -55.0), (1030.0, 50.0), (970.0, 60.0), (1000.0, 45.0), (1015.0, -60.0),
             (985.0, 50.0), (1050.0, 40.0), (960.0, -45.0), (1000.0, 65.0), (1020.0, 58.0), (990.0, -52.0)]
    shots = [{"pose": [{"id": "sq", "distance_mm": d, "tilt_deg": [0.0, t]}]} for d, t in poses]
    scene = scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": 600, "height_px": 400},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D},
        "render": {"samples_per_pixel": 256, "method": "raytrace"},
        "background": {"value": 0.25},
        "object": [{"id": "sq", "target": "slanted-edge", "distance_mm": 1000.0, "edge_mm": 60.0,
                    "size_mm": [150.0, 150.0], "angle_deg": 5.0}],
        "shot": shots})
    result = render(scene)
    out = tmp_path / "tilted"
    write_stack(result, out)
    f_px = result.truth["settings"]["a"]["focal_length_px"]
    (out / "stack.toml").write_text((out / "stack.toml").read_text()
                                    + f'\n[[intrinsics]]\nsetting = "a"\nfocal_length_px = {f_px}\n')
    s = f * D / (D - f)
    t = np.linspace(0.0, 1.0, 4001)
    errors = {1.0: [], BLUR_POWER_MEAN: [], 2.0: []}
    for x in measure(out).valid():
        local = (f / N) * s * np.abs(1 / D - 1 / (x.distance_start_mm + t * (x.distance_end_mm - x.distance_start_mm)))
        local /= pitch
        if local.max() < 1.5 * local.min() + 1.0:
            continue  # blur nearly constant along this edge: every mean agrees
        for q in errors:
            errors[q].append(x.coc_diameter_px / np.mean(local**q) ** (1 / q) - 1)
    assert len(errors[2.0]) >= 20
    err = {q: np.abs(v) for q, v in errors.items()}
    assert err[BLUR_POWER_MEAN].max() < 0.10, errors[BLUR_POWER_MEAN]
    assert err[BLUR_POWER_MEAN].mean() < err[1.0].mean() and err[BLUR_POWER_MEAN].mean() < err[2.0].mean()


def test_a_jpeg_stack_fits_like_the_linear_one(calibration_stack, calibration_samples, tmp_path):
    """A camera's JPEGs: 8-bit, sRGB-encoded (the default encoding for .jpg), quality 95. The
    stack, saved that way, is linearised on reading and fits f and the focus distance within
    1 % of the linear stack's fit; N within 6 % of the truth with its 95 % interval holding it
    (measured: -4.8 %, sigma about 3.5 %; -2.9 % with the profile's earlier per-band weights:
    compression softens edges of 0-3 px blur, so blur reads larger; read without linearising
    it would be far off)."""
    import shutil

    from PIL import Image

    from lensfit.io.images import read_image

    folder = tmp_path / "jpeg"
    folder.mkdir()
    for png in sorted(calibration_stack.glob("*.png")):
        linear = read_image(png)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)
        Image.fromarray(np.round(255 * srgb).astype(np.uint8)).save(folder / f"{png.stem}.jpg", quality=95)
        assert np.abs(read_image(folder / f"{png.stem}.jpg", "srgb") - linear).mean() < 0.01
    manifest = (calibration_stack / "stack.toml").read_text().replace(".png", ".jpg")
    (folder / "stack.toml").write_text(manifest)
    shutil.copy(calibration_stack / "truth.json", folder / "truth.json")
    truth = json.loads((calibration_stack / "truth.json").read_text())
    a, b = fit(calibration_samples), fit(measure(folder))
    assert b.code == "ok"
    assert b.focal_length_mm.value == pytest.approx(a.focal_length_mm.value, rel=0.01)
    n_true = truth["settings"]["a"]["f_number"]
    assert b.settings["a"]["f_number"].value == pytest.approx(n_true, rel=0.06)
    lo, hi = b.settings["a"]["f_number"].ci95
    assert lo <= n_true <= hi  # the interval knows: JPEG's errors are no noise the weights describe
    assert b.settings["a"]["focus_distance_mm"].value == pytest.approx(a.settings["a"]["focus_distance_mm"].value,
                                                                     rel=0.01)
