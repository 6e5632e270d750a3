"""Angles of view per setting (focus breathing), against the thin lens the stack was rendered with."""

from __future__ import annotations

import math

import pytest

from lensfit.optics.view import angles_of_view_deg, field_of_view


def test_angles_of_a_centred_pinhole_are_the_textbook_ones():
    """2 atan(W / 2f) across, and the diagonal's through the corners (written out here)."""
    h, w, f = 480, 640, 1000.0
    got = angles_of_view_deg(f, (h, w), ((w - 1) / 2, (h - 1) / 2))
    assert got["horizontal"] == pytest.approx(math.degrees(2 * math.atan(w / (2 * f))), rel=1e-12)
    assert got["vertical"] == pytest.approx(math.degrees(2 * math.atan(h / (2 * f))), rel=1e-12)
    assert got["diagonal"] == pytest.approx(math.degrees(2 * math.atan(math.hypot(w, h) / (2 * f))), rel=1e-12)
    # An off-centre principal point: the angle is the sum of the two sides' (not 2 atan of the half).
    off = angles_of_view_deg(f, (h, w), (100.0, (h - 1) / 2))
    assert off["horizontal"] == pytest.approx(math.degrees(math.atan(100.5 / f) + math.atan((w - 100.5) / f)))


def test_interval_follows_the_focal_lengths_with_students_t():
    fov = field_of_view(1000.0, 10.0, 4.0, (480, 640), (319.5, 239.5))["horizontal"]
    k = 2.7764451051977987  # t(0.975, 4)
    assert fov["ci95"][0] == pytest.approx(math.degrees(2 * math.atan(320 / (1000 + k * 10))), rel=1e-9)
    assert fov["ci95"][1] == pytest.approx(math.degrees(2 * math.atan(320 / (1000 - k * 10))), rel=1e-9)
    slope = math.degrees(2 * 320 / (1000.0**2 + 320.0**2))  # |d angle / d f|, per px
    assert fov["sigma"] == pytest.approx(slope * 10.0, rel=1e-4)


def test_a_fitted_stack_reports_the_angle_of_view_of_the_lens_it_was_rendered_with(calibration_stack, tmp_path):
    """The calibration stack (16 mm focused at 800 mm, 640 x 480 px of 6 um): the pinhole focal
    length is the sensor distance, 1 / (1/f - 1/D); its angles of view hold the truth."""
    import json

    from lensfit.cli import main

    out = tmp_path / "r.json"
    assert main(["fit", str(calibration_stack), "--out", str(out)]) in (0, 3)
    fov = json.loads(out.read_text())["calibration"]["a"]["field_of_view_deg"]
    s_mm = 1.0 / (1.0 / 16.0 - 1.0 / 800.0)
    for name, size_px in (("horizontal", 640), ("vertical", 480), ("diagonal", math.hypot(640, 480))):
        truth = math.degrees(2 * math.atan(size_px * 0.006 / (2 * s_mm)))
        assert fov[name]["ci95"][0] <= truth <= fov[name]["ci95"][1], (name, fov[name], truth)
        assert fov[name]["value"] == pytest.approx(truth, rel=0.005)
