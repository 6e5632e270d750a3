"""lensfit bench: the quick suite end to end, its report complete and its numbers consistent
with the per-case records; resume; the Dask executor on a local cluster started here."""

from __future__ import annotations

import base64
import json
import math
import sys
import time
from html.parser import HTMLParser
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from helpers import CHROMIUM, read_in_browser
from lensfit.bench.suites import load_suite
from lensfit.cli import main
from lensfit.bench.report import pareto


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "quick"
    # quick is a smoke suite: its camera-raw cases (noise, diffraction, a Bayer mosaic) may miss
    # the 1-2 % tolerances; the report is what is tested here, not those tolerances.
    started = time.perf_counter()
    assert main(["bench", "--suite", "quick", "--out", str(out), "--jobs", "2", "--allow-fail"]) == 0
    (out.parent / "outside_clock_s").write_text(repr(time.perf_counter() - started))
    return out


class _Images(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.headings, self.tables = [], [], 0
        self._in_h2 = False

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.images.append(dict(attrs))
        elif tag == "table":
            self.tables += 1
        self._in_h2 = tag == "h2"

    def handle_data(self, data):
        if self._in_h2:
            self.headings.append(data)
            self._in_h2 = False


def test_quick_report_is_complete(quick_report):
    suite = load_suite("quick")
    doc = json.loads((quick_report / "results.json").read_text())
    # An effects set that simulates the sensor gets no added noise level on top.
    sensor_sets = [fx for fx in suite.effects if {"exposure", "mosaic"} & set(fx.get("effects", []))]
    assert sensor_sets, "the quick suite renders one camera-raw (DNG) variant"
    plain_noises = [n for n in suite.noises if "full_well_e" not in n]
    per_grid = len(suite.seeds) * len(suite.renders) * len(suite.estimators) * len(suite.solvers)
    n_cases = per_grid * ((len(suite.effects) - len(sensor_sets)) * len(suite.noises)
                          + len(sensor_sets) * len(plain_noises))
    assert len(doc["cases"]) == n_cases
    raw_cases = [c for c in doc["cases"] if c["effects"] == sensor_sets[0]["name"]]
    assert raw_cases and all(c["noise"] == "none" for c in raw_cases)
    for c in raw_cases:  # DNG decoding, levels and demosaicing keep the fit on the lens
        for q, e in c["settings"]["a"].items():
            assert abs(e["relative_error"]) < 0.1, (q, e)
    for case in doc["cases"]:
        assert case["seconds_render"] > 0 and case["seconds_measure"] > 0 and case["seconds_fit"] > 0
        for q in ("focal_length_mm", "f_number", "focus_distance_mm"):
            e = case["settings"]["a"][q]
            assert e["truth"] > 0 and e["crlb"] is not None and e["crlb"] > 0
    for key in ("version", "command", "date", "cores", "seeds", "machine"):
        assert doc["provenance"][key] is not None
    parser = _Images()
    parser.feed((quick_report / "report.html").read_text())
    assert len(parser.images) == 5 and parser.tables >= 4
    for img in parser.images:
        assert img["src"].startswith("data:image/png;base64,")  # self-contained, readable offline
        png = iio.imread(base64.b64decode(img["src"].split(",", 1)[1]))
        assert png.shape[0] > 200 and png.std() > 5
    for heading in ("price of accuracy", "Calibration of the uncertainty", "Cramer-Rao", "Provenance",
                    "Estimated versus true"):
        assert any(heading in h for h in parser.headings), heading
    md = (quick_report / "report.md").read_text()
    for name in ("price_of_accuracy", "errors", "estimated_vs_true", "coverage", "efficiency"):
        assert f"plots/{name}.png" in md and (quick_report / "plots" / f"{name}.png").is_file()


@pytest.mark.skipif(CHROMIUM is None, reason="needs headless Chromium (Debian's package chromium; .ci/run installs it)")
def test_quick_report_reads_in_a_browser_at_800_px(quick_report, tmp_path):
    """The benchmark page in headless Chromium, 800 px wide: nothing wider than the window (the
    per-case tables scroll in their box), every plot decodes, an RMS error is never signed."""
    probe = read_in_browser(quick_report / "report.html", tmp_path)
    assert probe["scroll"] <= probe["client"] <= 800 and probe["wide"] == 0
    assert probe["images"] == 5 and probe["broken"] == 0
    for table in probe["tables"]:
        for col, name in enumerate(table[0]):
            if name == "RMS error":
                assert all(not row[col].startswith(("+", "-")) or row[col] == "-" for row in table[1:])


def test_bench_lenses_shows_p_only_where_the_bracket_fit_gave_every_quantity():
    from lensfit.cli.bench import p_fitted_text

    given = {"relative_error": 0.01}
    fit_row = {"result": "ok", "pupil_magnification": 1.2, "pupil_magnification_sigma": 0.05,
               "errors": {"focal_length_mm": given, "f_number": given, "focus_distance_mm": given}}
    assert p_fitted_text("thick (bracket, P fitted)", fit_row) == "1.200 ± 0.050"
    assert p_fitted_text("thin", fit_row) == ""
    refused = dict(fit_row, errors=dict(fit_row["errors"], f_number={"relative_error": None}))
    assert p_fitted_text("thick (bracket, P fitted)", refused) == ""
    assert p_fitted_text("thick (bracket, P fitted)", dict(fit_row, result="not_identifiable")) == ""


def test_a_design_rendered_at_its_own_field_sees_that_angle_with_the_same_pictures():
    """--field design: the sensor's half diagonal subtends the design's field at the focal length
    (capped at FIELD_CAP_DEG, never narrower than the demo's), and the boards and their offsets
    grow with the pixel pitch, so that each view frames its board as the demo's does."""
    from lensfit.bench.lenses import FIELD_CAP_DEG, lens_scene
    from synth.lens import load_prescription, paraxial

    efl = paraxial(load_prescription("cooke-triplet-50")).efl_mm
    demo = lens_scene("cooke-triplet-50", spp=1, scale=0.5)

    def half_field(scene):
        cam = scene["camera"]
        return math.degrees(math.atan(math.hypot(cam["width_px"], cam["height_px"]) * cam["pixel_pitch_mm"] / 2 / efl))

    for asked, seen in ((25.0, 25.0), (80.0, FIELD_CAP_DEG), (3.0, half_field(demo))):
        wide = lens_scene("cooke-triplet-50", spp=1, scale=0.5, field_deg=asked)
        assert half_field(wide) == pytest.approx(seen, rel=1e-9)
        q = wide["camera"]["pixel_pitch_mm"] / demo["camera"]["pixel_pitch_mm"]
        for a, b in zip(wide["object"], demo["object"]):
            assert a["square_mm"] == pytest.approx(q * b["square_mm"]) and a["distance_mm"] == b["distance_mm"]
            assert a["size_mm"] == pytest.approx([q * v for v in b["size_mm"]])
        for a, b in zip(wide["shot"], demo["shot"]):
            for pa, pb in zip(a.get("pose", []), b.get("pose", [])):
                assert pa["offset_mm"] == pytest.approx([q * v for v in pb["offset_mm"]])
                assert pa["distance_mm"] == pb["distance_mm"]


def test_bench_lenses_refuses_a_field_it_does_not_know_in_one_line(capsys):
    """--field design with the shipped designs (whose lens files state no field) is refused
    before anything is rendered, naming the option and the fix, exit 2."""
    from lensfit.cli import main

    assert main(["bench-lenses", "--field", "design", "--spp", "1", "--scale", "0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--field" in err[0] and "optiland" in err[0]


def test_bench_lenses_variants_never_write_one_record():
    """Each variant's --record is its own file, the existing ones' names kept: a run of one variant
    never replaces another's record."""
    import itertools

    from lensfit.bench.lenses import record_name

    variants = list(itertools.product(("wide", "narrow"), ("unit", "internal"), ("optiland", "shipped", "rayoptics"),
                                      (None, 5.6, 11.0, 2.8), ("demo", "design"), (0.5, 1.0, 0.25)))
    names = [record_name(*v) for v in variants]
    assert len(set(names)) == len(variants)
    assert record_name() == "lenses" and record_name("narrow", "internal") == "lenses_narrow_internal"
    assert record_name("wide", "unit", "optiland", 5.6) == "lenses_f5.6"
    assert record_name(scale=1.0) == "lenses_scale1"


@pytest.mark.parametrize("bracket, gap", [("wide", 1 / 8), ("narrow", 1 / 40)])
def test_bench_lenses_brackets_are_the_inverse_focus_gaps_the_issue_names(bracket, gap):
    """The scene bench-lenses renders: the two settings' focus distances (from the entrance
    pupil, as synth resolves them) 1/(8 f) or 1/(40 f) apart in inverse distance, the near
    setting's boards scaled with its distances."""
    from synth.lens import load_prescription, paraxial
    from synth.scene import scene_from_dict
    from lensfit.bench.lenses import BRACKETS, lens_scene

    f = paraxial(load_prescription("telephoto-250")).efl_mm
    scene = scene_from_dict(lens_scene("telephoto-250", near_fraction=BRACKETS[bracket]))
    X = {s.setting: s.camera.focus_distance_mm for s in scene.shots}
    assert (1 / X["near"] - 1 / X["far"]) * f == pytest.approx(gap, rel=1e-9)
    sizes = {label: sorted({o.target.params["square_mm"] for s in scene.shots if s.setting == label
                            for o in s.objects}) for label in ("near", "far")}
    assert len(sizes["far"]) == 2
    assert sizes["near"] == pytest.approx([BRACKETS[bracket] * v for v in sizes["far"]], rel=1e-12)


@pytest.mark.parametrize("hits, n", [(40, 40), (38, 40), (30, 40), (0, 5), (95, 100), (1, 1)])
def test_coverage_uncertainty_is_the_wilson_interval(hits, n):
    from scipy.stats import binomtest

    from lensfit.bench.report import wilson_interval

    ref = binomtest(hits, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert wilson_interval(hits, n) == pytest.approx([ref.low, ref.high], abs=1e-12)


def test_quick_report_numbers_agree_with_the_cases(quick_report):
    doc = json.loads((quick_report / "results.json").read_text())
    for q, c in doc["coverage"].items():  # every coverage with its binomial uncertainty
        lo, hi = c["coverage95_ci95"]
        assert lo <= c["coverage95"] <= hi and (hi - lo) > 0
    tol = doc["suite"]["tolerances"]
    for conf in doc["configurations"]:
        mine = [c for c in doc["cases"] if all(c[k] == conf[k] for k in ("scene", "render", "effects", "noise",
                                                                          "estimator", "solver"))]
        assert conf["cases"] == len(mine)
        for q, d in conf["quantities"].items():
            entries = [c["settings"]["a"][q] for c in mine]
            errs = np.array([e["value"] / e["truth"] - 1 for e in entries])
            assert d["passed"] == int(np.sum(np.abs(errs) <= tol[q]))
            assert d["rms_relative_error"] == pytest.approx(float(np.sqrt(np.mean(errs**2))))
            inside = [e["ci95"][0] <= e["truth"] <= e["ci95"][1] for e in entries]
            assert d["coverage95"] == pytest.approx(np.mean(inside))
            values = [e["value"] for e in entries]
            if len(values) >= 3:
                assert d["observed_scatter"] == pytest.approx(np.std(values, ddof=1) / entries[0]["truth"])
            else:  # two draws do not estimate a scatter (100 % relative uncertainty): none is claimed
                assert d["observed_scatter"] is None and d["efficiency"] is None
    # The Pareto front (per scene): no member is dominated, every other configuration is.
    for c in doc["configurations"]:
        others = [(o["seconds_measure_fit"], o["rms_relative_error"]) for o in doc["configurations"]
                  if o["scene"] == c["scene"]]
        t, e = c["seconds_measure_fit"], c["rms_relative_error"]
        dominated = any(t2 <= t and e2 <= e and (t2, e2) != (t, e) for t2, e2 in others)
        assert c["pareto_seconds_measure_fit"] == (not dominated)


def test_pareto_front_of_known_points():
    pts = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (4.0, 1.0), (5.0, 1.0), (None, 0.1)]
    assert pareto(pts) == [True, True, False, True, False, False]


def test_resume_keeps_finished_cases_and_refuses_a_used_folder(quick_report, capsys):
    cases = sorted((quick_report / "cache" / "cases").glob("*.json"))
    before = {p: p.stat().st_mtime_ns for p in cases}
    assert main(["bench", "--suite", "quick", "--out", str(quick_report)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["bench", "--suite", "quick", "--out", str(quick_report), "--resume", "--allow-fail"]) == 0
    assert {p: p.stat().st_mtime_ns for p in cases} == before  # nothing recomputed
    printed = capsys.readouterr().out
    coverage = json.loads((quick_report / "results.json").read_text())["coverage"]
    for q, c in coverage.items():  # the intervals' calibration printed as results.json has it
        line = next(x for x in printed.splitlines() if x.strip().startswith(f"{q}:"))
        assert f"{100 * c['coverage95']:.0f} % in the 95 % interval" in line
        assert f"error/sigma RMS {c['rms_error_over_sigma']:.2f}" in line
    prov = json.loads((quick_report / "results.json").read_text())["provenance"]
    assert "--resume" in prov["command"] and "--resume" not in prov["first_run"]["command"]


def test_seeds_replace_the_suites_and_a_resumed_run_runs_only_the_new_ones(quick_report, tmp_path, capsys):
    """``--seeds`` runs the suite's grid over other seeds: resumed on a copy of the quick run
    (seeds 0 and 1) with ``--seeds 1-2``, seed 1's finished cases are kept untouched, seed 2's are
    rendered and fitted, and the results, report and provenance hold seeds 1 and 2 only."""
    import shutil

    out = tmp_path / "quick"
    shutil.copytree(quick_report / "cache", out / "cache")
    before = {p.name: (json.loads(p.read_text())["seed"], p.stat().st_mtime_ns)
              for p in (out / "cache" / "cases").glob("*.json")}
    assert {seed for seed, _ in before.values()} == {0, 1}
    assert main(["bench", "--suite", "quick", "--out", str(out), "--resume", "--seeds", "1-2", "--allow-fail"]) == 0
    doc = json.loads((out / "results.json").read_text())
    per_seed = {s: sum(1 for c in doc["cases"] if c["seed"] == s) for s in (0, 1, 2)}
    assert per_seed[0] == 0 and per_seed[1] == per_seed[2] == sum(1 for s, _ in before.values() if s == 1)
    after = {p.name: p.stat().st_mtime_ns for p in (out / "cache" / "cases").glob("*.json")}
    assert all(after[name] == mtime for name, (_, mtime) in before.items())  # nothing redone or dropped
    assert len(after) == len(before) + per_seed[2]
    assert doc["provenance"]["seeds"] == [1, 2] and doc["provenance"]["first_run"]["seeds"] == [0, 1]


@pytest.mark.parametrize("spec", ["3-1", "a,b", "-1", "0,,2"])
def test_bad_seeds_are_refused_in_one_line_naming_the_option(spec, tmp_path, capsys):
    assert main(["bench", "--suite", "quick", "--out", str(tmp_path / "x"), "--seeds", spec]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--seeds" in err and repr(spec) in err and "e.g. 0-9" in err
    assert not (tmp_path / "x").exists()


def test_unknown_suite_names_the_available_ones(tmp_path, capsys):
    assert main(["bench", "--suite", "nonesuch", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "quick" in err and "standard" in err and "hard" in err


def test_dask_executor_on_a_local_cluster(tmp_path):
    """One case through Dask distributed: a LocalCluster started by the run, one worker process."""
    pytest.importorskip("distributed")
    suite = Path(load_suite("quick").path).read_text()
    small = (suite.split("\n# Effects sets")[0].replace("seeds = [0, 1]", "seeds = [3]")
             .replace('[[render]]\nmethod = "raytrace"\nsamples_per_pixel = 64\n', "")
             .replace('[[noise]]\nname = "iso1600"\nfull_well_e = 2000.0\nread_noise_e = 3.0\n', ""))
    (tmp_path / "bench_calibration.toml").write_text(
        (Path(load_suite("quick").scenes[0])).read_text())
    path = tmp_path / "tiny.toml"
    path.write_text(small)
    out = tmp_path / "out"
    assert main(["bench", "--suite", str(path), "--out", str(out), "--executor", "dask", "--jobs", "1",
                 "--allow-fail"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert len(doc["cases"]) == 1 and doc["provenance"]["executor"] == "dask"
    assert abs(doc["cases"][0]["settings"]["a"]["focus_distance_mm"]["value"] / 800.0 - 1) < 0.05


def test_a_case_outside_the_tolerances_makes_the_exit_status_non_zero(tmp_path, capsys):
    """FAIL rows in the report are a failed run (exit 4) unless --allow-fail says otherwise."""
    suite = Path(load_suite("quick").path).read_text()
    small = (suite.split("\n# Effects sets")[0].replace("seeds = [0, 1]", "seeds = [3]")
             .replace('[[render]]\nmethod = "raytrace"\nsamples_per_pixel = 64\n', "")
             .replace('[[noise]]\nname = "iso1600"\nfull_well_e = 2000.0\nread_noise_e = 3.0\n', "")
             .replace("focus_distance_mm = 0.02\n", "focus_distance_mm = 1e-9\n", 1))
    (tmp_path / "bench_calibration.toml").write_text(Path(load_suite("quick").scenes[0]).read_text())
    path = tmp_path / "strict.toml"
    path.write_text(small)
    assert main(["bench", "--suite", str(path), "--out", str(tmp_path / "a")]) == 4
    assert "outside the suite's tolerances" in capsys.readouterr().err
    assert main(["bench", "--suite", str(path), "--out", str(tmp_path / "a"), "--resume", "--allow-fail"]) == 0


def test_bench_stages_makes_a_larger_stack_from_its_images_again_and_measures_memory(tmp_path):
    """--shots beyond the stack's own: its photographs again, in turn, under new names (a valid
    stack); a process's peak memory read from wait4 grows with what it holds."""
    import tomllib

    from lensfit.bench.stages import subset
    from lensfit.io.stack import load_stack

    src = tmp_path / "src"
    src.mkdir()
    names = [f"im{k}.png" for k in range(3)]
    for k, name in enumerate(names):
        iio.imwrite(src / name, np.full((8, 12), 1000 * (k + 1), np.uint16))
    board = ('id = "b"\nkind = "charuco"\nsquares = [5, 4]\nsquare_mm = 10.0\nmarker_mm = 7.0\n'
             'dictionary = "DICT_4X4_50"')
    (src / "stack.toml").write_text(f"[camera]\npixel_pitch_mm = 0.01\n\n[[target]]\n{board}\n\n"
                                    + "".join(f'[[image]]\nfile = "{n}"\nsetting = "a"\n\n' for n in names))
    out = subset(src, tmp_path / "big", 7, 1.0)
    files = [e["file"] for e in tomllib.loads((out / "stack.toml").read_text())["image"]]
    assert len(files) == len(set(files)) == 7 and files[:3] == names
    for k, name in enumerate(files):
        assert np.array_equal(iio.imread(out / name), iio.imread(src / names[k % 3]))
    assert len(load_stack(out).images) == 7
    from lensfit.bench.peak import run_with_peak

    small = run_with_peak([sys.executable, "-c", "x = 1"], 60)
    large = run_with_peak([sys.executable, "-c", "import numpy as np; x = np.ones(400 * 2**20 // 8); x += 1"], 60)
    assert small.status == large.status == 0
    assert small.peak_bytes < 100 * 2**20 < 400 * 2**20 < large.peak_bytes - small.peak_bytes < 500 * 2**20
    # its CPU seconds: a process that spins for 0.6 s of CPU reports at least that, and no more than it ran
    busy = run_with_peak([sys.executable, "-c", "import time\nt = time.process_time()\n"
                          "while time.process_time() - t < 0.6: pass"], 60)
    assert 0.6 <= busy.cpu_seconds <= busy.seconds * 2 and small.cpu_seconds < 0.6


def test_bench_stages_refuses_what_it_cannot_compare(tmp_path, capsys):
    assert main(["bench-stages", str(tmp_path)]) == 2
    assert "no stack.toml" in capsys.readouterr().err
    (tmp_path / "stack.toml").write_text('[camera]\npixel_pitch_mm = 0.006\n[[target]]\nid = "s"\nkind = "slanted-edge"\n')
    assert main(["bench-stages", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "slanted-edge" in err and "ChArUco" in err and len(err.strip().splitlines()) == 1


def test_render_time_leaves_out_compilation_only():
    """A fresh jitted function with a long trace and a trivial run: nearly all of its first call
    is compilation (JAX's own events), none of its second; nested jit spans count once."""
    import jax
    import jax.numpy as jnp

    from lensfit.bench.runs import without_compilation

    @jax.jit
    def inner(x):
        for k in range(60):
            x = jnp.sin(x) * (1.0 + k * 1e-3)
        return x

    @jax.jit
    def outer(x):
        for _ in range(20):
            x = inner(x) + 1.0
        return x

    x = jnp.ones(3)
    out, seconds, compiling = without_compilation(lambda: outer(x).block_until_ready())
    assert out.shape == (3,)
    # the split, not the speed: no fixed figure (a quick machine compiles this in under 50 ms)
    assert compiling > 0.0
    assert seconds < 0.5 * compiling  # the run itself is microseconds
    _, seconds2, compiling2 = without_compilation(lambda: outer(x).block_until_ready())
    assert compiling2 == 0.0


def test_bench_lenses_never_replaces_a_kept_stack_and_reuses_only_what_is_there(tmp_path, capsys):
    """--keep refuses a folder already holding a stack of that name (before rendering anything,
    leaving it as it was); --reuse refuses a folder without the stacks; both name the option and
    the folder in one line with a non-zero exit."""
    kept = tmp_path / "kept" / "cooke-triplet-50"
    kept.mkdir(parents=True)
    (kept / "mine.txt").write_text("a user's file")
    assert main(["bench-lenses", "--lens", "cooke-triplet-50", "--keep", str(tmp_path / "kept")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--keep" in err and str(tmp_path / "kept") in err and "cooke-triplet-50" in err and "\n" not in err
    assert [p.name for p in kept.iterdir()] == ["mine.txt"] and (kept / "mine.txt").read_text() == "a user's file"
    assert main(["bench-lenses", "--lens", "cooke-triplet-50", "--reuse", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--reuse" in err and str(tmp_path / "empty") in err and "----" not in err and "\n" not in err


@pytest.mark.parametrize("spp", [8, 16])
def test_effects_sets_share_the_geometric_render_bit_for_bit(tmp_path, spp):
    # A scene drawn as written, with diffraction and as a camera's raw DNG shares one geometric
    # render (lensfit.bench.runs.run_group): the images are those of separate renders bit for
    # bit; a render with another seed or another aperture shares nothing. At 16 spp diffraction
    # acts on the render at four times the resolution (one stratum a cell), which the shared
    # render keeps; at 8 (not a square) on the image as sampled.
    from lensfit.bench.suites import scene_with_effects
    from synth.effects.diffraction import APPLIED_SAMPLED, applied_fine
    from synth.rendering import GeometricCache, render

    scene = tmp_path / "s.toml"
    scene.write_text("""
name = "s"
[camera]
pixel_pitch_mm = 0.006
width_px = 96
height_px = 64
[lens]
focal_length_mm = 25.0
f_number = 8.0
focus_distance_mm = 1000.0
[render]
samples_per_pixel = 8
seed = 0
[[object]]
id = "board"
target = "checkerboard"
squares = [5, 4]
square_mm = 6.0
distance_mm = 700.0
tilt_deg = [20.0, 10.0]
""")
    sets = [{"name": "scene"},
            {"name": "diffraction", "effects": ["defocus", "diffraction"], "diffraction": {"wavelength_nm": 550.0}},
            {"name": "camera-raw", "effects": ["defocus", "diffraction", "vignetting", "exposure", "mosaic", "noise"],
             "exposure": {"shutter_s": 0.01, "iso": 400, "luminance_cd_m2": 2000.0},
             "sensor": {"preset": "aps-c-24mp"}}]
    shared = GeometricCache()
    for fx in sets:
        alone = render(scene_with_effects(scene, fx), method="raytrace", samples_per_pixel=spp)
        together = render(scene_with_effects(scene, fx), method="raytrace", samples_per_pixel=spp,
                          geometric_cache=shared)
        if fx["name"] != "scene":
            assert together.truth["images"][0]["diffraction"]["applied"] == (applied_fine(4) if spp == 16
                                                                             else APPLIED_SAMPLED)
        for name, image in alone.images.items():
            assert np.array_equal(image, together.images[name]), (fx["name"], name)
        for name, raw in alone.raw.items():
            assert np.array_equal(raw, together.raw[name]), (fx["name"], name)
    assert len(shared.entries) == 1 and len(shared.hits) == 2  # drawn once, handed out twice
    render(scene_with_effects(scene, sets[0]), method="raytrace", samples_per_pixel=spp, seed=1, geometric_cache=shared)
    polygon = {"name": "hexagon", "effects": ["defocus", "aperture"], "aperture": {"shape": "polygon", "blades": 6}}
    render(scene_with_effects(scene, polygon), method="raytrace", samples_per_pixel=spp, geometric_cache=shared)
    assert len(shared.entries) == 3 and len(shared.hits) == 2


def test_a_shared_render_is_timed_with_its_own_seconds_less_compilation():
    # The seconds a task that takes a shared render adds for it: the render's window less the
    # union of JAX's compile spans within it (overlapping spans counted once).
    from lensfit.bench.runs import warm_seconds

    assert warm_seconds((0.0, 10.0), [(1.0, 3.0), (2.0, 4.0), (8.0, 12.0)]) == pytest.approx(5.0)
    assert warm_seconds((0.0, 10.0), []) == pytest.approx(10.0)
    assert warm_seconds((5.0, 6.0), [(0.0, 20.0)]) == 0.0


def test_design_effect_reads_the_correlation_it_was_drawn_with():
    """Random-effects draws (a group's shared part with variance rho, its own with 1 - rho):
    the estimator finds rho, and none where the groups share nothing."""
    from lensfit.bench.report import design_effect

    rng = np.random.default_rng(5)
    for rho in (0.0, 0.3, 0.8):
        sizes = rng.integers(4, 12, size=300)
        groups = [list(math.sqrt(rho) * rng.normal() + math.sqrt(1 - rho) * rng.normal(size=m)) for m in sizes]
        est, deff = design_effect(groups)
        assert est == pytest.approx(rho, abs=0.06), (rho, est)
        assert deff == pytest.approx(1 + (sizes.mean() - 1) * est)
    assert design_effect([[0.1, 0.3], [0.2, 0.5]]) == (1.0, 2.0)  # too few groups: each counts once


def test_copies_of_the_same_intervals_do_not_narrow_the_coverage_interval():
    """Every interval counted k times (as a case's noise levels and solver settings nearly copy
    one render's intervals) says no more about the coverage than counted once: the interval of
    the coverage stays that of the distinct intervals, where taking them as independent narrows
    it by sqrt(k)."""
    from lensfit.bench.report import coverage_summary, wilson_interval

    rng = np.random.default_rng(1)
    rows = []
    for seed in range(30):
        z = rng.standard_t(6)
        for copy in range(6):
            rows.append({"quantity": "f_number", "scene": "demo", "render": "raytrace 16 spp", "seed": seed,
                         "value": 1.0 + 0.01 * z, "truth": 1.0, "sigma": 0.01, "in68": abs(z) <= 1.0,
                         "in95": abs(z) <= 1.96})
    cov = coverage_summary(rows)["f_number"]
    hits = sum(r["in95"] for r in rows[::6])
    assert cov["intervals"] == 180 and cov["intervals_effective"] == pytest.approx(30.0)
    assert cov["coverage95_ci95"] == pytest.approx(wilson_interval(hits, 30), abs=1e-9)
    lo, hi = cov["coverage95_ci95_if_independent"]
    assert hi - lo < 0.6 * (cov["coverage95_ci95"][1] - cov["coverage95_ci95"][0])


def _rows_for(errors, sigmas, z95=1.959963984540054):
    return [{"quantity": "f_number", "scene": "demo", "render": "r", "seed": k, "effects": "scene",
             "value": 10.0 + e, "truth": 10.0, "sigma": s, "half95": z95 * s,
             "in68": abs(e) <= s, "in95": abs(e) <= z95 * s} for k, (e, s) in enumerate(zip(errors, sigmas))]


def test_interval_honesty_reads_gaussian_errors_as_right_and_wide_sigmas_as_wide():
    """Against what a Gaussian gives in closed form: with the right sigmas, RMS error over sigma 1,
    mean 95 % half-width over mean |error| 1.96 / sqrt(2 / pi) = 2.46, the reliability curve on
    the diagonal, and the 95 % coverage at a matched 68 % 95 %; sigmas stated twice too large
    halve the first, double the second, and leave the shape (the matched coverage) alone."""
    from lensfit.bench.report import GAUSSIAN_HALF_WIDTH_RATIO, interval_honesty

    rng = np.random.default_rng(11)
    sigma = rng.uniform(0.01, 0.1, size=40000)
    err = sigma * rng.standard_normal(sigma.size)
    right = interval_honesty(_rows_for(err, sigma))
    assert GAUSSIAN_HALF_WIDTH_RATIO == pytest.approx(2.4565, abs=1e-4)
    assert right["rms_error_over_sigma"] == pytest.approx(1.0, abs=0.01)
    assert right["z68"] == pytest.approx(1.0, abs=0.02)
    assert right["coverage95_at_matched_68"] == pytest.approx(0.95, abs=0.005)
    for point in right["reliability"]:
        assert point["observed"] == pytest.approx(point["nominal"], abs=0.006)
    # a sigma-weighted mean |error| against a sigma-weighted mean half-width: 1.96 / E|Z| either way
    assert right["half_width95_over_mean_error"] == pytest.approx(GAUSSIAN_HALF_WIDTH_RATIO, rel=0.02)
    wide = interval_honesty(_rows_for(err, 2.0 * sigma))
    assert wide["rms_error_over_sigma"] == pytest.approx(0.5, abs=0.005)
    assert wide["half_width95_over_mean_error"] == pytest.approx(2.0 * GAUSSIAN_HALF_WIDTH_RATIO, rel=0.02)
    assert wide["coverage95_at_matched_68"] == pytest.approx(right["coverage95_at_matched_68"], abs=1e-3)
    assert all(p["observed"] > p["nominal"] for p in wide["reliability"])


def test_interval_honesty_tells_light_and_heavy_tails_from_width():
    """The 95 % coverage once the intervals are rescaled to cover 68 % exactly: 1 for errors
    bounded within 1.34 times their 68 % quantile (uniform: |z| uniform, its 68.27 % quantile
    0.6827 of the bound), and for Student's t with 3 degrees of freedom what its distribution
    function gives (below 95 %: heavy tails)."""
    from scipy.stats import t as student

    from lensfit.bench.report import interval_honesty

    rng = np.random.default_rng(12)
    n = 40000
    sigma = np.full(n, 0.05)
    uniform = interval_honesty(_rows_for(rng.uniform(-0.05, 0.05, n), sigma))
    assert uniform["z68"] == pytest.approx(0.6827, abs=0.01)
    assert uniform["coverage95_at_matched_68"] == 1.0
    heavy = interval_honesty(_rows_for(0.05 * rng.standard_t(3, n), sigma))
    q68 = student.ppf(0.5 + 0.6827 / 2, 3)
    expected = 2 * student.cdf(1.959963984540054 * q68, 3) - 1
    assert heavy["z68"] == pytest.approx(q68, rel=0.02)
    assert heavy["coverage95_at_matched_68"] == pytest.approx(expected, abs=0.005)
    assert heavy["coverage95_at_matched_68"] < 0.94


def test_the_coverage_summary_carries_the_honesty_per_effects_set():
    from lensfit.bench.report import coverage_summary, interval_honesty

    rng = np.random.default_rng(13)
    rows = _rows_for(0.05 * rng.standard_normal(300), np.full(300, 0.05))
    for k, r in enumerate(rows):
        r["effects"] = "diffraction" if k % 3 == 0 else "scene"
    cov = coverage_summary(rows)["f_number"]
    both = interval_honesty(rows)
    assert cov["rms_error_over_sigma"] == pytest.approx(both["rms_error_over_sigma"])
    assert set(cov["by_effects"]) == {"diffraction", "scene"}
    diff = [r for r in rows if r["effects"] == "diffraction"]
    d = cov["by_effects"]["diffraction"]
    assert d["errors"] == len(diff) == 100
    assert d["rms_error_over_sigma"] == pytest.approx(interval_honesty(diff)["rms_error_over_sigma"])
    assert d["coverage95"] == pytest.approx(np.mean([r["in95"] for r in diff]))


def test_parallel_workers_get_the_costliest_groups_first():
    # Every group of the standard suite handed out once, the most samples per pixel first, the
    # suite's order kept among equals (the records come back in suite order whatever the order
    # of the work).
    from lensfit.bench.runs import costliest_first, groups

    suite_groups = groups(load_suite("standard").tasks())
    ordered = costliest_first(suite_groups)
    assert sorted(map(id, ordered)) == sorted(map(id, suite_groups))
    spp = [g[0]["render"]["samples_per_pixel"] for g in ordered]
    assert spp == sorted(spp, reverse=True) and spp[0] > spp[-1]
    for value in set(spp):
        same = [g for g in suite_groups if g[0]["render"]["samples_per_pixel"] == value]
        assert [g for g in ordered if g[0]["render"]["samples_per_pixel"] == value] == same


def test_a_noisy_stack_in_memory_holds_the_pixels_its_written_copy_decodes_to(calibration_stack, tmp_path):
    """The benchmark's noisy stacks are held in memory (``noisy_stack``) instead of written as PNG
    copies and read back (``noisy_copy``): every image is the copy's decoded image to the bit,
    from the same seed, and noisy (not the clean image). A stack whose files would decode
    otherwise (sRGB-encoded) is refused, for the caller to write the copy."""
    from lensfit.bench.noise import noisy_copy, noisy_stack
    from lensfit.io.stack import load_stack

    held = noisy_stack(calibration_stack, np.random.default_rng(7), 2000.0, 3.0, 0.8)
    noisy_copy(calibration_stack, tmp_path / "copy", np.random.default_rng(7), 2000.0, 3.0, 0.8)
    copy, clean = load_stack(tmp_path / "copy"), load_stack(calibration_stack)
    assert held is not None and len(held.images) == len(copy.images) >= 6
    rng = np.random.default_rng(7)  # the noise model written out: photons, read noise, 16 bits
    for i in range(len(copy.images)):
        electrons = rng.poisson(np.clip(clean.read(i), 0.0, 1.0) * 0.8 * 2000.0) + rng.normal(0.0, 3.0, clean.shape)
        expected = np.round(np.clip(electrons / 2000.0, 0.0, 1.0) * 65535).astype(np.uint16) / 65535.0
        assert held.read(i).dtype == copy.read(i).dtype == np.float64
        assert np.array_equal(copy.read(i), expected)
        assert np.array_equal(held.read(i), copy.read(i))
        assert np.std(held.read(i) - 0.8 * np.clip(clean.read(i), 0.0, 1.0)) > 1e-3
    srgb = tmp_path / "srgb"
    noisy_copy(calibration_stack, srgb, np.random.default_rng(0), 2000.0, 3.0)
    manifest = srgb / "stack.toml"
    manifest.write_text(manifest.read_text().replace('encoding = "linear"', 'encoding = "srgb"'))
    assert 'encoding = "srgb"' in manifest.read_text()
    assert noisy_stack(srgb, np.random.default_rng(0), 2000.0, 3.0) is None


def test_the_results_say_how_long_the_run_took(quick_report):
    """The provenance carries the run's wall seconds (rendering, measuring, fitting): for the
    first run most of what the command took by an outside clock and never more; a resumed run
    (the resume test here, with nothing left to do) its own seconds beside the first run's."""
    doc = json.loads((quick_report / "results.json").read_text())
    first = json.loads((quick_report / "cache" / "provenance.json").read_text())
    outside = float((quick_report.parent / "outside_clock_s").read_text())
    assert 0.5 * outside <= first["seconds_wall"] <= outside
    if "first_run" in doc["provenance"]:
        assert doc["provenance"]["first_run"]["seconds_wall"] == first["seconds_wall"]
        assert doc["provenance"]["seconds_wall"] < 0.5 * first["seconds_wall"]
    else:
        assert doc["provenance"]["seconds_wall"] == first["seconds_wall"]


def test_a_resumed_run_redoes_a_truncated_or_edited_case(quick_report, tmp_path, capsys):
    """A case file cut short (a crash of another tool, a full disk) or edited to another case's
    record is not a finished case: ``--resume`` runs that case again and replaces the file,
    instead of failing on it."""
    import shutil

    out = tmp_path / "quick"
    shutil.copytree(quick_report, out)
    cases = sorted((out / "cache" / "cases").glob("*.json"))
    cut, swapped = cases[0], cases[1]
    cut.write_text(cut.read_text()[:40])
    swapped.write_text(cases[2].read_text())
    assert main(["bench", "--suite", "quick", "--out", str(out), "--resume", "--allow-fail"]) == 0, \
        capsys.readouterr().err
    for f in (cut, swapped):
        assert json.loads(f.read_text())["id"] == f.stem


def test_bench_hostile_records_each_case_and_fails_a_case_that_misses(tmp_path, capsys, monkeypatch):
    """Two quick cases through the command: the record holds each case's status, time and peak
    memory, the table shows them; a case whose expected message is not met makes the command
    exit 4 and is marked failed."""
    from lensfit.bench import hostile

    only = ["target_squares_1e5", "samples_json_nested_100k"]
    assert main(["bench-hostile", "--only", *only, "--record", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "hostile.json").read_text())
    assert [c["name"] for c in doc["cases"]] == only and doc["passed"] == 2
    for c in doc["cases"]:
        assert c["status"] == 2 and 0 < c["seconds"] < hostile.MAX_SECONDS and 0 < c["peak_mib"] < 1024
    assert "target[0].squares" in doc["cases"][0]["message"] and "| 2 |" in hostile.markdown(doc)
    assert main(["bench-hostile", "--only", "nope"]) == 2
    real = hostile.CASES["target_squares_1e5"]

    def wrong_expectation(root):
        case = real(root)
        case.expect_text = "a message the program never writes"
        return case

    monkeypatch.setitem(hostile.CASES, "target_squares_1e5", wrong_expectation)
    capsys.readouterr()
    assert main(["bench-hostile", "--only", "target_squares_1e5", "--json"]) == 4
    assert json.loads(capsys.readouterr().out)["cases"][0]["passed"] is False


def test_bench_developed_judges_refusals_by_the_processing_named_and_strips_only_software(tmp_path):
    """A developed stack passes on f and focus within 0.5 % and N within 1.5 % or refused naming
    the processing; a refusal that names nothing fails, as does any refusal of the control. The
    Software-less copy keeps every other EXIF tag."""
    from PIL import Image

    from lensfit.bench.developed import row_passed, without_software

    good = {"refused": False, "relative_error": 0.001, "inside": True}
    refused = {"refused": True, "reason": "developed"}
    named = {"developer": "darktable 4.2.1", "halos": False}
    errors = {"focal_length_mm": good, "f_number": refused, "focus_distance_mm": good}
    assert row_passed(errors, named, control=False)
    assert not row_passed(errors, {"developer": None, "halos": False}, control=False)
    assert row_passed(errors, {"developer": None, "halos": False, "tone_mismatch": True}, control=False)
    assert not row_passed(errors, named, control=True)
    assert not row_passed(dict(errors, f_number={"refused": False, "relative_error": 0.06, "inside": False}), named,
                       control=False)
    assert not row_passed(dict(errors, focal_length_mm=refused), named, control=False)
    src = tmp_path / "src"
    src.mkdir()
    exif = Image.Exif()
    exif[0x010F], exif[0x0131] = "Canon", "darktable 4.2.1"
    pixels = (np.arange(64 * 48, dtype=np.uint8).reshape(48, 64))
    Image.fromarray(pixels).save(src / "a.jpg", "JPEG", quality=95, exif=exif)
    without_software(src, tmp_path / "dst")
    with Image.open(tmp_path / "dst" / "a.jpg") as im:
        tags = im.getexif()
        assert 0x0131 not in tags and tags[0x010F] == "Canon"
        assert np.abs(np.asarray(im, float) - np.asarray(Image.open(src / "a.jpg"), float)).max() <= 4


def test_bench_developed_declares_the_controls_lens_in_the_drafted_stack(tmp_path):
    """The drafted stack.toml gains the control's [lens] table as TOML that reads back to the same
    values, and keeps everything init wrote."""
    import tomllib

    from lensfit.bench.developed import declare_lens

    control, drafted = tmp_path / "control.toml", tmp_path / "drafted.toml"
    control.write_text('[camera]\npixel_pitch_mm = 0.006\n\n[lens]\nfocusing = "unit"\n'
                       'pupil_magnification = 1.0\nideal = true\n')
    drafted.write_text('[camera]\npixel_pitch_mm = 0.006\n\n[[image]]\nfile = "a.jpg"\nencoding = "srgb"\n')
    declare_lens(control, drafted)
    got = tomllib.loads(drafted.read_text())
    assert got["lens"] == {"focusing": "unit", "pupil_magnification": 1.0, "ideal": True}
    assert got["image"] == [{"file": "a.jpg", "encoding": "srgb"}] and got["camera"] == {"pixel_pitch_mm": 0.006}


def test_bench_developed_runs_the_in_camera_pipeline_whatever_developers_are_installed(tmp_path):
    """The pipeline written here needs no program (its name holds a comma, like darktable's
    variant, which alone waits on darktable's JPEGs)."""
    from lensfit.bench.developed import program_for

    assert program_for("in-camera pipeline, no EXIF", ("", ""), tmp_path) == ""
    assert program_for("darktable, Software tag removed", ("sh", "darktable"), tmp_path) is None
    (tmp_path / "darktable" / "photos").mkdir(parents=True)
    assert program_for("darktable, Software tag removed", ("sh", "darktable"), tmp_path).endswith("sh")
    assert program_for("rawtherapee", ("no-such-program-here", "rawtherapee"), tmp_path) is None


def test_bench_developed_scene_at_another_f_number_keeps_the_light_on_the_sensor():
    """Exposure H = L t / N^2 (the camera equation): two stops more aperture, a quarter of the
    time; the lens and the shots are otherwise the scene's own."""
    from lensfit.bench.developed import scene_at
    from lensfit.io.specs import specs_dir
    from synth.scene import load_scene

    own, faster = load_scene(specs_dir() / "scenes" / "camera_raw.toml"), scene_at(5.5)
    assert len(faster.shots) == len(own.shots)
    for a, b in zip(own.shots, faster.shots):
        assert a.camera.f_number == 11.0 and b.camera.f_number == 5.5
        assert b.camera.focal_length_mm == a.camera.focal_length_mm
        assert b.camera.focus_distance_mm == a.camera.focus_distance_mm
        t_own = a.shutter_s or own.effects.exposure.shutter_s
        t_fast = b.shutter_s or faster.effects.exposure.shutter_s
        assert t_own / a.camera.f_number**2 == pytest.approx(t_fast / b.camera.f_number**2, rel=1e-12)
        assert t_fast == pytest.approx(t_own / 4, rel=1e-12)


def test_bench_developed_coverage_leaves_out_the_controls_and_counts_refusals_apart():
    """Over the developed stacks alone: 2 of 3 intervals held (Wilson 0.208-0.939, worked from
    the score formula), a refusal not counted as reported."""
    from lensfit.bench.developed import coverage

    def row(stack, n):
        ok = {"refused": False, "relative_error": 0.001, "inside": True}
        return {"stack": stack, "errors": {"focal_length_mm": ok, "focus_distance_mm": ok, "f_number": n}}
    held = {"refused": False, "relative_error": 0.01, "inside": True}
    missed = {"refused": False, "relative_error": -0.03, "inside": False}
    rows = [row("DNG (control)", missed), row("darktable", held), row("rawtherapee", {"refused": True}),
            row("in-camera pipeline, no EXIF", missed), row("darktable, Software tag removed", held),
            {"stack": "rawtherapee", "missing": "not found"}]
    got = coverage(rows)
    assert (got["f_number"]["held"], got["f_number"]["reported"], got["f_number"]["refused"]) == (2, 3, 1)
    assert got["f_number"]["wilson95"] == pytest.approx([0.2077, 0.9385], abs=5e-4)
    assert got["f_number"]["mean_abs_error"] == pytest.approx(0.05 / 3)
    assert (got["focal_length_mm"]["held"], got["focal_length_mm"]["reported"]) == (4, 4)


def test_bench_lenses_coverage_counts_both_settings_and_takes_wilsons_interval():
    """Counted per quantity over both settings, a refusal apart from the intervals, with Wilson's
    score interval (1 of 2: 0.095-0.905, worked by hand from the score formula)."""
    from lensfit.bench.lenses import coverage
    held = {"relative_error": 0.01, "within_ci95": True}
    missed = {"relative_error": 0.2, "within_ci95": False}
    refused = {"relative_error": None, "within_ci95": None}
    rows = [{"fits": {"bracket": {"errors": {"focal_length_mm": held, "f_number": refused},
                                  "errors_far": {"focal_length_mm": missed, "f_number": held}}}}]
    got = coverage(rows)["bracket"]
    assert (got["focal_length_mm"]["held"], got["focal_length_mm"]["reported"]) == (1, 2)
    assert got["focal_length_mm"]["wilson95"] == pytest.approx([0.0945, 0.9055], abs=5e-4)
    assert (got["f_number"]["held"], got["f_number"]["reported"], got["f_number"]["refused"]) == (1, 1, 1)
    assert got["focus_distance_mm"]["rate"] is None


def test_bench_lenses_record_sets_the_mean_error_beside_the_mean_half_width():
    """Means over the bounded intervals only (an open one has no width), worked by hand; P
    counted where the fit estimated it; the record's table shows both and the coverage."""
    from lensfit.bench.lenses import coverage, markdown
    a = {"relative_error": 0.01, "within_ci95": True, "half_width_relative": 0.03}
    b = {"relative_error": -0.03, "within_ci95": False, "half_width_relative": 0.02}
    open_ = {"relative_error": 0.02, "within_ci95": True, "half_width_relative": None}
    p = {"relative_error": 0.1, "within_ci95": True, "half_width_relative": 0.2}
    rows = [{"lens": "x", "fits": {"bracket": {"errors": {"focal_length_mm": a, "pupil_magnification": p},
                                               "errors_far": {"focal_length_mm": b}}}},
            {"lens": "y", "fits": {"bracket": {"errors": {"focal_length_mm": open_}}}}]
    got = coverage(rows)["bracket"]
    assert (got["focal_length_mm"]["held"], got["focal_length_mm"]["reported"]) == (2, 3)
    assert got["focal_length_mm"]["mean_abs_error"] == pytest.approx(0.02)
    assert got["focal_length_mm"]["mean_half_width"] == pytest.approx(0.025)
    assert (got["pupil_magnification"]["held"], got["pupil_magnification"]["mean_half_width"]) == (1, 0.2)
    text = markdown({"coverage": {"bracket": got}, "rows": [], "samples_per_pixel": 16, "scale": 0.5,
                     "f_number": None, "designs": "optiland"})
    assert "| bracket | f | 2 of 3 (" in text and "| 2.00 % | 2.50 % | 1.25 |" in text
    assert "| bracket | P | 1 of 1 (" in text


def test_optiland_designs_written_as_lens_files_keep_optilands_paraxial_data(tmp_path):
    """The lens files bench-lenses --designs optiland renders through: read back by synth, each
    design's EFL and pupil magnification are optiland's own (its paraxial solver, not ours)."""
    pytest.importorskip("optiland")
    import warnings

    from lensfit.bench.designs import lens_file_text, sample_objectives
    from synth.lens.files import load_prescription
    from synth.lens.prescription import paraxial

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import optiland.samples.objectives as objectives

        for name, rx, fno in list(sample_objectives())[:4]:
            path = tmp_path / f"{name}.toml"
            path.write_text(lens_file_text(rx, name, "optiland", fno))
            back = paraxial(load_prescription(path))
            lens = getattr(objectives, name)()
            assert back.efl_mm == pytest.approx(float(lens.paraxial.f2()), rel=1e-6), name
            assert back.f_number == pytest.approx(fno, rel=1e-6), name


def test_rayoptics_designs_written_as_lens_files_trace_as_rayoptics_traces_them(tmp_path, monkeypatch):
    """The lens files bench-lenses --designs rayoptics renders through, read back by synth: every
    photographic sample rayoptics reads (CODE V, Zemax and its own files) is taken, with
    rayoptics's own EFL and pupil magnification (its paraxial solver), and a real ray at 0.7 of the
    pupil leaves the last surface where rayoptics's exact trace puts it, at its angle. Reading
    them leaves nothing in the working directory (rayoptics's readers log to files there)."""
    pytest.importorskip("rayoptics")
    import numpy as np
    from rayoptics.raytr.raytrace import trace as rayoptics_trace

    import rayoptics
    from lensfit.bench.designs import RAYOPTICS_SAMPLES, lens_file_text, rayoptics_objectives, read_rayoptics
    from synth.lens.files import load_prescription
    from synth.lens.prescription import paraxial, trace

    here = tmp_path / "cwd"
    here.mkdir()
    monkeypatch.chdir(here)
    found = list(rayoptics_objectives())
    assert len(found) == len(RAYOPTICS_SAMPLES)
    assert list(here.iterdir()) == []
    for name, rx, fno, source, _ in found:
        path = tmp_path / f"{name}.toml"
        path.write_text(lens_file_text(rx, name, source, fno))
        back = load_prescription(path)
        para = paraxial(back)
        opm = read_rayoptics(Path(rayoptics.__file__).parent / source.removeprefix("rayoptics/"))
        fod = opm["analysis_results"]["parax_data"].fod
        assert para.efl_mm == pytest.approx(fod.efl, rel=1e-6), name
        assert para.pupil_magnification == pytest.approx(fod.exp_radius / fod.enp_radius, rel=1e-6), name
        assert para.f_number == pytest.approx(fod.fno, rel=1e-6), name
        # a ray parallel to the axis at 0.7 of the entrance pupil's radius, both tracers to the last surface
        h = 0.7 * fod.enp_radius
        sm = opm["seq_model"]
        segments = rayoptics_trace(sm, np.array([0.0, h, 0.0]), np.array([0.0, 0.0, 1.0]),
                                   opm["optical_spec"]["wvls"].central_wvl)[0]
        last = len(sm.ifcs) - 2
        (_, y, _), (_, dy, dz), passed, _ = trace(back, (np.zeros(1), np.full(1, h), np.full(1, -1.0)),
                                                  (np.zeros(1), np.zeros(1), np.ones(1)))
        assert passed[0], name
        assert float(y[0]) == pytest.approx(segments[last][0][1], abs=1e-6), name
        assert float(dy[0] / dz[0]) == pytest.approx(segments[last][1][1] / segments[last][1][2], rel=1e-6), name


def test_a_case_other_code_measured_is_not_a_finished_case(monkeypatch):
    """A case's id holds the digest of lensfit's sources: the same case under the same code keeps
    its id (a resumed run keeps it), under other code it is another case (run again)."""
    from lensfit.bench import suites
    from lensfit.io.specs import specs_dir

    task = {"scene": str(specs_dir() / "scenes" / "demo.toml"), "render": {"method": "convolve"}, "seed": 0}
    case = {"noise": "none", "estimator": "edge", "solver": {"loss": "huber"}}
    here = suites.case_id(task, case)
    assert suites.case_id(task, case) == here
    monkeypatch.setattr(suites, "code_digest", lambda: "another version")
    assert suites.case_id(task, case) != here


def test_bench_lenses_makes_a_design_it_cannot_render_a_row_saying_why():
    """A design the bench cannot render as asked (here: an image 100 times the demo's, beyond the
    scene schema's largest side) is a row naming the refusal, not the end of the whole run (an
    optiland wide-angle's pixel pitch at half scale fell below the schema's least, and every
    design's results before it were lost)."""
    from lensfit.bench.lenses import run

    rows = run(names=["cooke-triplet-50"], scale=100.0, spp=1)["rows"]
    assert len(rows) == 1 and rows[0]["lens"] == "cooke-triplet-50" and rows[0]["fits"] == {}
    assert rows[0]["refused"].startswith("not rendered: ") and "width_px" in rows[0]["refused"]
