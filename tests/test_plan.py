"""``lensfit plan``: its Cramer-Rao bound is the fit's own (an independent code path: JAX
Jacobian of the full model on samples built at the planned distances), its distance range obeys
the stated limits, and it chooses the smallest capture that reaches the goal."""

from __future__ import annotations

import json
import math

import pytest

from lensfit.cli import main as lensfit_main
from lensfit.plan import Board, bound, plan_capture

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
    from lensfit.fit import cramer_rao, fit

    rows, fpx = samples_at(distances)
    res = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=0.001 * fpx,
              pupil_magnification=1.0, loss="linear")
    assert res.ok
    ref = cramer_rao(res, F, {"a": (N, X)})["a"]
    ours = bound(F, N, 1 / X, 1 / __import__("numpy").array(distances), BOARD, PITCH, edge_sigma_px=0.05,
                 edge_sigma_rel=0.02, calibration_sigma_rel=0.001)
    for q, true in (("focal_length_mm", F), ("f_number", N), ("focus_distance_mm", X)):
        assert ours[q] == pytest.approx(ref[q] / true, rel=0.01), q


def test_plan_is_the_smallest_capture_reaching_the_goal_inside_the_usable_range():
    goal = 0.004
    plan = plan_capture(F, N, X, pixel_pitch_mm=PITCH, width_px=3000, height_px=2000, board=BOARD, goal_rel=goal)
    assert plan.shots is not None and plan.shots == len(plan.distances_mm)
    reached = [all(1.96 * row[q] <= goal for q in ("focal_length_mm", "f_number", "focus_distance_mm"))
               for row in plan.curve]
    assert reached[plan.shots - 3] and not any(reached[:plan.shots - 3])
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
