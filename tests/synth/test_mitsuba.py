"""Stacks from another renderer: Mitsuba 3's thinlens camera (``method = "mitsuba"``,
synth/mitsuba.py) against the CoC formula and synth's own ray tracer, and the fit on its
images against the truth they were rendered from."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from lensfit.errors import InputError
from synth.raytrace import render_raytrace
from synth.rendering import render
from synth.scene import scene_from_dict
from synth.stack import write_stack
from test_synth_render import disk_esf  # the disk's edge-spread function, written out there

from synth.mitsuba import find_libllvm, render_mitsuba  # noqa: E402

find_libllvm()  # before Mitsuba's import, which is when Dr.Jit takes libLLVM's path
pytest.importorskip("mitsuba")


def variant_or_skip(variant: str) -> str:
    """The variant, or a skip where it cannot start here (llvm_ad_rgb needs libLLVM 20 or later,
    which the test extra installs on Linux x86_64: karellen-llvm-core)."""
    from synth.mitsuba import load_mitsuba

    try:
        load_mitsuba(variant)
    except InputError as e:
        pytest.skip(str(e))
    return variant


def make_scene(objects, *, f=50.0, N=2.8, D=2000.0, w=96, h=96, pitch=0.006, background=0.0, spp=64, render=None,
               lens=None):
    return scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D, **(lens or {})},
        "render": {"samples_per_pixel": spp, "seed": 0, **(render or {})},
        "background": {"value": background},
        "object": objects,
    })


@pytest.mark.parametrize("N, d, variant", [(2.0, 1400.0, "scalar_rgb"), (4.0, 3000.0, "scalar_rgb"),
                                           (2.0, 1400.0, "llvm_ad_rgb")])
def test_mitsuba_edge_profile_is_the_cocs_disk(N, d, variant):
    # Mitsuba's defocus through synth's mapping (field of view from the sensor distance, aperture
    # radius A/2, focus distance) against the CoC formula A s |1/D - 1/d| / p: the disk diameter
    # and edge position fitted to its edge profile (disk ESF with pixel integration) match.
    from scipy.optimize import least_squares

    f, D, pitch = 50.0, 2000.0, 0.006
    s = 1.0 / (1.0 / f - 1.0 / D)
    c = (f / N) * s * abs(1.0 / D - 1.0 / d) / pitch
    mm_per_px = pitch * d / s
    edge_px, width = 10.3, 1000 * mm_per_px
    obj = {"target": "uniform", "value": 1.0, "distance_mm": d, "size_mm": [width, 400 * mm_per_px],
           "offset_mm": [edge_px * mm_per_px + width / 2, 0.0]}
    W, H = 160, 64
    shot = make_scene([obj], f=f, N=N, D=D, w=W, h=H, pitch=pitch).shots[0]
    profile = render_mitsuba(shot, 0.0, 1024, 5, variant=variant_or_skip(variant))[4:-4].mean(axis=0).astype(np.float64)
    u = np.arange(W) - (W - 1) / 2
    fine = (np.arange(64) + 0.5) / 64 - 0.5

    def model(p):  # p = (diameter px, edge px)
        return disk_esf(u[:, None] + fine[None, :] - p[1], p[0] / 2).mean(axis=1)

    fitted = least_squares(lambda p: model(p) - profile, x0=[1.1 * c, edge_px + 0.3]).x
    assert c > 10  # a blur the profile resolves
    assert fitted[0] == pytest.approx(c, rel=0.005)  # seen: within 0.1 %
    assert fitted[1] == pytest.approx(edge_px, abs=0.02)
    assert np.max(np.abs(model(fitted) - profile)) < 6e-3  # the shape is the disk's (noise 2e-3)


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb"])
def test_mitsuba_and_synth_draw_the_same_tilted_board(variant):
    # Two renderers, one scene (a tilted ChArUco board, 13-19 px of blur across it): no shift
    # (a 0.1 px offset of the board reads 0.09 px here), no mirror, and no difference beyond
    # their Monte-Carlo noise (which two Mitsuba renders with other seeds show).
    board = {"target": "charuco", "squares": [5, 4], "square_mm": 6.0, "marker_mm": 4.5, "dictionary": "DICT_4X4_50",
             "size_mm": [34.0, 28.0], "distance_mm": 1100.0, "offset_mm": [1.0, -0.7], "tilt_deg": [20.0, -25.0]}
    shot = make_scene([board], N=5.6, D=1500.0, w=112, h=96, background=0.3).shots[0]
    ours = render_raytrace(shot, 0.3, 256, 1).astype(np.float64)
    theirs, again = (render_mitsuba(shot, 0.3, 256, k, variant=variant_or_skip(variant)).astype(np.float64)
                     for k in (1, 2))
    diff = theirs - ours
    gy, gx = np.gradient(ours)
    shift = np.linalg.lstsq(np.stack([gx.ravel(), gy.ravel()], axis=1), diff.ravel(), rcond=None)[0]
    assert np.all(np.abs(shift) < 0.02), shift  # px; seen 0.001

    def local(d):  # largest 5 x 5 px mean difference
        return np.abs(ndimage.uniform_filter(d, 5)[4:-4, 4:-4]).max()

    assert local(diff) < 1.2 * local(theirs - again)  # seen 0.023 against 0.029
    assert abs(diff.mean()) < 1e-3
    assert np.std(theirs[30:66, 30:82]) > 0.1  # the board is there, with contrast


def test_an_llvm_too_old_for_mitsubas_kernels_is_refused_not_a_crash():
    # libLLVM 19 and older abort the process on Mitsuba 3.9's kernels ("Cannot select: fmaximum");
    # a system's libLLVM 15, where there is one, gets a one-line refusal naming the fix instead.
    import glob
    import os
    import subprocess
    import sys

    old = sorted(glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM-1[0-9].so*"))
    if not old:
        pytest.skip("no libLLVM older than 20 on this machine")
    code = ("from lensfit.errors import InputError\nfrom synth.mitsuba import load_mitsuba\n"
            "try:\n    load_mitsuba('llvm_ad_rgb')\nexcept InputError as e:\n    print('refused:', e)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, "DRJIT_LIBLLVM_PATH": old[-1]}, timeout=120)
    assert proc.returncode == 0, proc.stderr[-500:]
    assert "refused:" in proc.stdout and "karellen-llvm-core" in proc.stdout and "20 or later" in proc.stdout


def test_mitsuba_refuses_what_it_cannot_render():
    board = {"target": "checkerboard", "squares": [4, 4], "square_mm": 5.0, "distance_mm": 1000.0}
    polygon = make_scene([board], render={"method": "mitsuba", "effects": ["defocus", "aperture"]},
                         lens={"aperture": {"shape": "polygon", "blades": 6}})
    with pytest.raises(InputError, match="mitsuba.*polygon aperture"):
        render(polygon)
    edge = make_scene([{"target": "slanted-edge", "distance_mm": 1000.0, "size_mm": [20.0, 20.0]}],
                      render={"method": "mitsuba"})
    with pytest.raises(InputError, match="slanted-edge"):
        render(edge)


@pytest.fixture(scope="module")
def mitsuba_stack(tmp_path_factory):
    """The conftest's calibration stack (8 ChArUco views, 640 x 480, f/8), drawn by Mitsuba."""
    from helpers import calibration_scene

    scene = scene_from_dict(calibration_scene(samples_per_pixel=32, method="mitsuba"))
    out = tmp_path_factory.mktemp("mitsuba") / "calib"
    write_stack(render(scene), out)
    return out


def test_a_mitsuba_stack_fits_to_its_truth(mitsuba_stack):
    import lensfit
    from lensfit.measurement.measure import measure

    truth = json.loads((mitsuba_stack / "truth.json").read_text())
    assert truth["method"] == "mitsuba" and truth["renderer"].startswith("Mitsuba 3")
    result = lensfit.fit(measure(mitsuba_stack))
    assert result.code == "ok", result.reasons
    setting = truth["settings"]["a"]
    expected = {"focal_length_mm": truth["focal_length_mm"], "f_number": setting["f_number"],
                "focus_distance_mm": setting["focus_distance_mm"]}
    for name, true in expected.items():
        est = result.settings["a"][name] if name != "focal_length_mm" else result.focal_length_mm
        assert est.value == pytest.approx(true, rel=0.015), name
        lo, hi = est.ci95
        assert lo <= true <= hi, (name, est.value, est.ci95, true)
