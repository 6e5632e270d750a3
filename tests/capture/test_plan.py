"""``lensfit plan``: its Cramer-Rao bound is the fit's own (an independent code path: JAX
Jacobian of the full model on samples built at the planned distances), its distance range obeys
the stated limits, and it chooses the smallest capture that reaches the goal."""

from __future__ import annotations

import json
import math

import pytest

from lensfit.cli import main as lensfit_main
from lensfit.capture.plan import MIN_SHOTS, Board, bound, plan_capture

F, N, X, PITCH = 25.0, 4.0, 1000.0, 0.006
BOARD = Board(270.0, 180.0, 30.0, 67)


def samples_at(distances, sigma_px=0.05, sigma_rel=0.02):
    S = 1 / (1 / F - 1 / X)
    rows = []
    for d in distances:
        c = (F / N) * S * abs(1 / d - 1 / X) / PITCH  # thin-lens blur, written out here
        for e in range(BOARD.edges):
            rows.append({"image": f"shot-{d:.0f}", "setting": "a", "edge": str(e), "distance_mm": d,
                         "coc_diameter_px": c, "sigma_px": math.hypot(sigma_px, sigma_rel * c)})
    return rows, S / PITCH


@pytest.mark.parametrize("distances", [[450.0, 700.0, 1600.0, 2400.0], [1200.0, 1500.0, 2500.0, 4000.0, 6000.0]])
def test_plan_bound_equals_the_fits_cramer_rao(distances):
    from lensfit.fitting import cramer_rao, fit

    rows, fpx = samples_at(distances)
    res = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=0.001 * fpx,
              pupil_magnification=1.0, loss="linear")
    assert res.ok
    ref = cramer_rao(res, F, {"a": (N, X)})["a"]
    ours = bound(F, N, 1 / X, 1 / __import__("numpy").array(distances), BOARD, PITCH, edge_sigma_px=0.05,
                 edge_sigma_rel=0.02, calibration_sigma_rel=0.001, distances_scale=False)
    for q, true in (("focal_length_mm", F), ("f_number", N), ("focus_distance_mm", X)):
        assert ours[q] == pytest.approx(ref[q] / true, rel=0.01), q


def test_plan_is_the_smallest_capture_reaching_the_goal_inside_the_usable_range():
    goal = 0.004
    plan = plan_capture(F, N, X, pixel_pitch_mm=PITCH, width_px=3000, height_px=2000, board=BOARD, goal_rel=goal)
    assert plan.shots is not None and plan.shots == len(plan.distances_mm)
    reached = [all(1.96 * row[q] <= goal for q in ("focal_length_mm", "f_number", "focus_distance_mm"))
               for row in plan.curve]
    assert plan.shots == max(reached.index(True) + 3, MIN_SHOTS)  # never below the calibration's views
    near, far = plan.usable_mm
    assert near < X < far  # this sensor and board allow both sides of focus
    S = 1 / (1 / F - 1 / X)
    for d in (near, far):
        mag = S / d
        square_px = BOARD.square_mm * mag / PITCH
        blur_px = (F / N) * S * abs(1 / d - 1 / X) / PITCH
        assert BOARD.width_mm * mag <= 0.9 * 3000 * PITCH * 1.001 and square_px >= 24 * 0.999
        assert blur_px <= 0.25 * square_px * 1.001
    # at the near end some limit binds: the board fills the frame or the blur reaches a quarter square
    mag = S / near
    assert (BOARD.width_mm * mag >= 0.9 * 3000 * PITCH * 0.99
            or (F / N) * S * abs(1 / near - 1 / X) / PITCH >= 0.25 * BOARD.square_mm * mag / PITCH * 0.99)
    # many shots beat few (evenly spaced captures are not nested: the curve need not be monotonic)
    for q in ("f_number", "focus_distance_mm"):
        assert plan.curve[-1][q] < plan.curve[0][q]


def test_plan_cli_one_side_note_json_and_refusals(capsys):
    assert lensfit_main(["plan", "--focal-length", "25", "--f-number", "11", "--focus-distance", "1000",
                         "--sensor", "demo-7.2x4.8"]) == 0
    out = capsys.readouterr().out
    assert "one side of focus" in out and "usable target distances" in out
    assert lensfit_main(["plan", "--focal-length", "50", "--f-number", "2.8", "--focus-distance", "2000",
                         "--sensor", "full-frame-24mp", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["shots"] is not None and doc["usable_distance_mm"][0] < 2000 < doc["usable_distance_mm"][1]
    # focus nearer than the focal length: refused naming the option
    assert lensfit_main(["plan", "--focal-length", "25", "--f-number", "11", "--focus-distance", "20",
                         "--sensor", "demo-7.2x4.8"]) == 2
    assert "--focus-distance" in capsys.readouterr().err
    assert lensfit_main(["plan", "--focal-length", "25", "--f-number", "11", "--focus-distance", "1000"]) == 2
    assert "--sensor" in capsys.readouterr().err


@pytest.mark.slow
def test_the_usable_range_measures_when_rendered():
    """Shots rendered by synth at both ends of the plan's usable range, for a ChArUco board whose
    clean room and markers bind before its squares do, measure: the markers decode and most of
    the board's edges give a blur reading (none cut short by the clean room)."""
    from lensfit.measurement.measure import measure
    from synth.rendering import render
    from synth.scene import scene_from_dict
    from synth.stack import write_stack
    import tempfile
    from pathlib import Path

    f, n, x, pitch, w, h = 16.0, 2.0, 900.0, 0.006, 960, 640
    entry = {"kind": "charuco", "squares": [6, 4], "square_mm": 30.0, "marker_mm": 22.0, "dictionary": "DICT_4X4_50"}
    board = Board.from_entry(entry)
    plan = plan_capture(f, n, x, pixel_pitch_mm=pitch, width_px=w, height_px=h, board=board)
    near, far = plan.usable_mm
    scene = {"camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
             "lens": {"focal_length_mm": f, "f_number": n, "focus_distance_mm": x},
             "render": {"samples_per_pixel": 16}, "background": {"value": 0.3},
             "object": [{"id": "board", "target": "charuco", "squares": [6, 4], "square_mm": 30.0,
                         "marker_mm": 22.0, "dictionary": "DICT_4X4_50", "size_mm": [190.0, 130.0],
                         "distance_mm": x}],
             "shot": [{"pose": [{"id": "board", "distance_mm": d, "tilt_deg": t}]} for d, t in (
                 (near * 1.01, [0, 0]), (far * 0.99, [0, 0]), (x, [25, 0]), (0.8 * x, [0, -25]))]}
    with tempfile.TemporaryDirectory() as tmp:
        write_stack(render(scene_from_dict(scene)), Path(tmp) / "s")
        table = measure(Path(tmp) / "s", refine=False)
    for image in ("shot_000.png", "shot_001.png"):  # the near and the far end
        mine = [s for s in table.samples if s.image == image]
        read = [s for s in mine if s.coc_diameter_px is not None]
        assert len(read) >= 0.8 * board.edges and not any("window_truncated" in s.flags for s in mine), image


def test_a_calibration_error_scales_every_distance_and_so_f_n_and_x_alike():
    """The limit of perfect edges: what is left of each bound is the calibration's focal length in
    px, whose relative error scales every pose distance, and with them f, N and X by the same
    factor (written out: c = (f/N) S |1/d - 1/X| / p is unchanged when d, X, S and f scale
    together with N, the aperture f/N kept)."""
    import numpy as np

    w = 1 / np.array([450.0, 700.0, 1600.0, 2400.0])
    b = bound(F, N, 1 / X, w, BOARD, PITCH, edge_sigma_px=1e-9, edge_sigma_rel=1e-9, calibration_sigma_rel=0.003)
    for q in ("focal_length_mm", "f_number", "focus_distance_mm"):
        assert b[q] == pytest.approx(0.003, rel=1e-3), q
    held = bound(F, N, 1 / X, w, BOARD, PITCH, edge_sigma_px=1e-9, edge_sigma_rel=1e-9, calibration_sigma_rel=0.003,
                 distances_scale=False)
    assert held["focus_distance_mm"] < 1e-4  # distances held exact: the focus distance would owe nothing to it


@pytest.mark.slow
def test_a_planned_capture_measures_and_reaches_the_plans_accuracy(tmp_path):
    """Plan a capture, render the planned shots with synth (the distances as planned, turned by
    20-25 degrees in turn as the checklist asks), fit: every planned shot gives readings, the fit's
    sigmas are within 1.5x of the plan's bounds, its 95 % intervals reach the goal and hold the
    truth."""
    from lensfit.fitting import fit
    from lensfit.measurement.measure import measure
    from synth.rendering import render
    from synth.scene import scene_from_dict
    from synth.stack import write_stack

    f, n, x, pitch, w, h = 16.0, 2.8, 900.0, 0.006, 960, 640
    entry = {"kind": "charuco", "squares": [6, 4], "square_mm": 30.0, "marker_mm": 22.0, "dictionary": "DICT_4X4_50"}
    board = Board.from_entry(entry)
    plan = plan_capture(f, n, x, pixel_pitch_mm=pitch, width_px=w, height_px=h, board=board, goal_rel=0.01)
    tilts = [[0, 0], [25, 0], [0, -25], [-20, 15], [0, 25], [20, -20]]
    scene = {"camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
             "lens": {"focal_length_mm": f, "f_number": n, "focus_distance_mm": x},
             "render": {"samples_per_pixel": 16}, "background": {"value": 0.3},
             "object": [{"id": "board", "target": "charuco", **{k: v for k, v in entry.items() if k != "kind"},
                         "size_mm": [190.0, 130.0], "distance_mm": x}],
             "shot": [{"pose": [{"id": "board", "distance_mm": d, "tilt_deg": tilts[k % len(tilts)]}]}
                      for k, d in enumerate(plan.distances_mm)]}
    write_stack(render(scene_from_dict(scene)), tmp_path / "s")
    table = measure(tmp_path / "s")
    assert plan.shots == len(plan.distances_mm) >= 6
    for k in range(plan.shots):
        read = [s for s in table.samples if s.image == f"shot_{k:03d}.png" and s.coc_diameter_px is not None]
        assert len(read) >= 0.7 * board.edges, k
    res = fit(table)
    for q, true in (("focal_length_mm", f), ("f_number", n), ("focus_distance_mm", x)):
        e = res.settings["a"][q]
        assert e.sigma / true <= 1.5 * plan.sigma[q], q
        lo, hi = e.ci95
        assert lo < true < hi and (hi - lo) / 2 / true <= plan.goal_rel, q


def test_the_plan_prints_as_a_one_page_shot_list(tmp_path, capsys):
    """--shot-list: one A4 page (read back by PDFium) listing every planned distance with a turn of
    the board, the promised accuracy and the checklist; not replaced without --force."""
    pdfium = pytest.importorskip("pypdfium2")
    out = tmp_path / "shots.pdf"
    args = ["plan", "--focal-length", "50", "--f-number", "2.8", "--focus-distance", "2000", "--sensor",
            "full-frame-24mp", "--shot-list", str(out)]
    assert lensfit_main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    pdf = pdfium.PdfDocument(str(out))
    assert len(pdf) == 1
    w_pt, h_pt = pdf[0].get_size()
    assert (w_pt / 72 * 25.4, h_pt / 72 * 25.4) == pytest.approx((210.0, 297.0), abs=0.05)
    page = pdf[0].get_textpage()
    text = page.get_text_range()
    right = max(page.get_charbox(i)[2] for i in range(page.count_chars()))
    assert right <= w_pt - 20  # every line inside the page, a margin to spare
    for d in doc["distances_mm"]:
        assert f"{d:.0f}" in text
    for word in ("face on", "25 deg away", "autofocus off", "RAW", "Predicted 95 % half-intervals"):
        assert word in text
    assert lensfit_main(args) == 2 and "--force" in capsys.readouterr().err
    assert lensfit_main(args + ["--force"]) == 0
    assert lensfit_main(args[:-1] + [str(tmp_path / "shots.txt")]) == 2
    png = args[:-1] + [str(tmp_path / "shots.png")]
    assert lensfit_main(png) == 0 and lensfit_main(png + ["--force"]) == 0  # its own PNG is replaced
