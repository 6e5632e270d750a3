"""Fixtures shared by the test modules: stacks rendered once per session."""

from __future__ import annotations

import pytest
from hypothesis import settings

# Property tests draw the same examples on every run (the repository's rule: deterministic given
# a seed); a failure found once stays reproducible instead of appearing at random in CI.
settings.register_profile("deterministic", derandomize=True)
settings.load_profile("deterministic")

from synth.render import render
from synth.scene import scene_from_dict
from synth.stack import write_stack


@pytest.fixture(scope="session")
def calibration_stack(tmp_path_factory):
    """A small ChArUco stack (8 shots, some tilted) rendered by synth."""
    shots = []
    for k, (dist, tilt) in enumerate([(450, [0, 0]), (550, [25, 0]), (650, [0, -30]), (800, [-20, 15]),
                                      (950, [0, 25]), (1100, [20, -20]), (1300, [0, 0]), (1500, [-25, 10])]):
        shots.append({"pose": [{"id": "board", "distance_mm": float(dist), "tilt_deg": tilt}]})
    scene = scene_from_dict({
        "camera": {"pixel_pitch_mm": 0.006, "width_px": 640, "height_px": 480},
        "lens": {"focal_length_mm": 16.0, "f_number": 8.0, "focus_distance_mm": 800.0},
        "render": {"samples_per_pixel": 64},
        "background": {"value": 0.3},
        "object": [{"id": "board", "target": "charuco", "squares": [6, 4], "square_mm": 30.0, "marker_mm": 22.0,
                    "dictionary": "DICT_4X4_50", "size_mm": [190.0, 130.0], "distance_mm": 800.0}],
        "shot": shots,
    })
    out = tmp_path_factory.mktemp("stack") / "calib"
    write_stack(render(scene), out)
    return out


@pytest.fixture(scope="session")
def calibration_samples(calibration_stack):
    """The calibration stack measured with the edge estimator (shared: measuring takes seconds)."""
    from lensfit.measure import measure

    return measure(calibration_stack)
