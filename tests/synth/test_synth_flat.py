"""synth.flat: the pixels the ray tracer takes as constant instead of sampling them.

Checked two ways: against the same tracer sampling every pixel (the image must not change), and
against the geometry written out here (a pixel far from every edge of a fronto-parallel board
is constant, one whose blur disk reaches an edge is not)."""

import math

import numpy as np
import pytest

from synth import flat
from synth.raytrace import camera_array, render_raytrace, scene_arrays
from synth.scene import scene_from_dict


def make_shot(objects, *, f=50.0, N=2.8, D=2000.0, w=97, h=71, pitch=0.006, lens=None, effects=None):
    render = {"samples_per_pixel": 16, "seed": 0, "method": "raytrace"}
    if effects:
        render["effects"] = effects
    return scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D, **(lens or {})},
        "render": render,
        "background": {"value": 0.3},
        "object": objects,
    }).shots[0]


def charuco(distance, **extra):
    return {"target": "charuco", "squares": [5, 4], "square_mm": 8.0, "marker_mm": 6.0,
            "dictionary": "DICT_4X4_50", "size_mm": [44.0, 36.0], "distance_mm": distance, **extra}


CASES = {
    # a board tilted 60 degrees through the plane of focus at f/1.4: blur from 0 to large across it
    "tilted-through-focus": (dict(N=1.4, D=1000.0), [charuco(1000.0, tilt_deg=[0.0, 60.0])], {}),
    # 1:2 macro: a 50 mm lens focused at 150 mm, checkerboard squares of a millimetre
    "macro": (dict(N=8.0, D=150.0), [{"target": "checkerboard", "squares": [6, 5], "square_mm": 1.0,
                                       "distance_mm": 160.0, "tilt_deg": [20.0, 0.0]}], {}),
    # focus at infinity: a uniform patch and a slanted edge square (never declared constant)
    "infinity": (dict(N=4.0, D="inf"), [
        {"id": "patch", "target": "uniform", "value": 0.8, "size_mm": [300.0, 200.0], "distance_mm": 8000.0,
         "offset_mm": [-200.0, 0.0]},
        {"id": "edge", "target": "slanted-edge", "size_mm": [200.0, 200.0], "distance_mm": 6000.0,
         "offset_mm": [150.0, 0.0]}], {}),
    # a card in front of a board, blurred over each other's edges: two objects touched
    "occlusion": (dict(N=8.0, D=900.0), [
        {"id": "board", **charuco(1000.0)},
        {"id": "card", "target": "uniform", "value": 0.9, "size_mm": [4.0, 4.0], "distance_mm": 800.0,
         "offset_mm": [2.0, 1.5]}], {}),
    # bladed and squeezed apertures
    "polygon": (dict(N=8.0, D=900.0, lens={"aperture": {"shape": "polygon", "blades": 5, "rotation_deg": 10.0}}),
                [charuco(1100.0, tilt_deg=[15.0, 10.0])], {"effects": ["defocus", "aperture"]}),
    "anamorphic-wide": (dict(N=8.0, D=900.0, lens={"aperture": {"shape": "anamorphic", "squeeze": 0.6}}),
                        [charuco(1100.0)], {"effects": ["defocus", "aperture"]}),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_constant_pixels_leave_the_image_unchanged(name):
    kw, objects, extra = CASES[name]
    shot = make_shot(objects, **kw, **extra)
    aperture = ("circle",)
    if "aperture" in kw.get("lens", {}):
        from synth.effects.aperture import Aperture

        aperture = Aperture.from_spec(kw["lens"]["aperture"]).static
    structure, rasters, planes = scene_arrays(shot)
    cam = shot.camera
    constant = flat.constant_pixels(structure, rasters, planes, camera_array(cam), cam.width_px, cam.height_px, 0.3,
                                    aperture)
    known = np.isfinite(constant)
    assert 0.05 < known.mean() < 1.0  # some pixels decided, some traced: both paths exercised
    for spp, fine in ((16, 1), (64, 4)):
        full = render_raytrace(shot, 0.3, spp, 3, aperture=aperture, fine=fine, constant_regions=False)
        fast = render_raytrace(shot, 0.3, spp, 3, aperture=aperture, fine=fine)
        if fine > 1:
            (full, full_fine), (fast, fast_fine) = full, fast
            assert np.allclose(fast_fine, full_fine, rtol=0.0, atol=1e-6)
        assert np.array_equal(fast[~known], full[~known])  # the traced pixels: the same samples
        # the constant ones: the mean of identical samples (float32 rounding of that mean)
        assert np.allclose(fast[known], full[known], rtol=0.0, atol=1e-6)
        assert np.allclose(constant[known], full[known], rtol=0.0, atol=1e-6)


def test_constant_pixels_follow_the_blur_disk():
    # A fronto-parallel checkerboard: by the thin-lens formulas written out here, a pixel whose
    # square (grown by the blur radius) stays inside one board square is constant at that
    # square's value; one whose blur disk reaches an edge line must be traced.
    f, N, D, d, pitch = 50.0, 16.0, 1200.0, 1000.0, 0.006
    sq, nx, ny, w, h = 3.0, 4, 3, 144, 112
    shot = make_shot([{"target": "checkerboard", "squares": [nx, ny], "square_mm": sq, "size_mm": [nx * sq, ny * sq],
                       "dark": 0.1, "light": 0.8, "distance_mm": d}], f=f, N=N, D=D, w=w, h=h, pitch=pitch)
    structure, rasters, planes = scene_arrays(shot)
    cam = shot.camera
    constant = flat.constant_pixels(structure, rasters, planes, camera_array(cam), w, h, 0.3)
    s = 1.0 / (1.0 / f - 1.0 / D)
    px_per_mm = s / (d * pitch)  # magnification on the sensor, in px per board mm
    blur_radius_px = 0.5 * (f / N) * s * abs(1.0 / D - 1.0 / d) / pitch
    assert 2.0 < blur_radius_px < 0.25 * sq * px_per_mm
    ys, xs = np.mgrid[0:h, 0:w]
    u = (xs - (w - 1) / 2) / px_per_mm + 0.5 * nx * sq  # board mm from its top-left corner
    v = (ys - (h - 1) / 2) / px_per_mm + 0.5 * ny * sq
    # distance (board mm) from the pixel centre to the nearest square edge line inside the board
    to_edge = np.minimum(np.abs(u - sq * np.round(u / sq)), np.abs(v - sq * np.round(v / sq)))
    on_board = (u > 0) & (u < nx * sq) & (v > 0) & (v < ny * sq)
    half_pixel = 0.5 * math.sqrt(2.0) / px_per_mm
    reach = blur_radius_px / px_per_mm + half_pixel  # the pixel's rays spread no further
    must_trace = on_board & (to_edge < blur_radius_px / px_per_mm - half_pixel)
    assert must_trace.any() and not np.isfinite(constant[must_trace]).any()
    # the decision is by 4 px blocks grown by the octagon about the aperture: 4 px and 8 % slack
    block = 4.0 * math.sqrt(2.0) / px_per_mm
    surely = on_board & (to_edge > 1.1 * reach + block)
    assert surely.sum() > 300 and np.isfinite(constant[surely]).all()
    i, j = np.floor(u[surely] / sq), np.floor(v[surely] / sq)
    expected = np.where((i + j) % 2 == 0, 0.1, 0.8)  # top-left square dark (synth.textures)
    assert np.array_equal(constant[surely], expected.astype(np.float32))
    far = (np.abs(u - 0.5 * nx * sq) > 0.5 * nx * sq + 1.1 * reach + block) | \
          (np.abs(v - 0.5 * ny * sq) > 0.5 * ny * sq + 1.1 * reach + block)
    assert far.any() and np.all(constant[far] == np.float32(0.3))  # the background beside the board


@pytest.mark.parametrize("k1", [-0.3, 0.25])
def test_constant_pixels_under_lens_distortion(k1):
    # Barrel and pincushion distortion strong enough to bend a board's edges by pixels: each
    # traced sample follows its own undistorted ray (the warp), and the blocks' boxes hold them.
    from synth.effects.distortion import Distortion, pixel_warp

    shot = make_shot([charuco(230.0, tilt_deg=[20.0, 0.0], offset_mm=[30.0, 20.0])], f=6.0, N=2.8, D=200.0,
                     w=161, h=121, pitch=0.02)
    warp = pixel_warp(shot.camera, Distortion(k1=k1))
    corner = np.hypot(*(warp[0, 0, :2] - np.array([80.0, 60.0]))) - np.hypot(80.0, 60.0)
    assert abs(corner) > 2.0  # the corners moved by pixels
    structure, rasters, planes = scene_arrays(shot)
    constant = flat.constant_pixels(structure, rasters, planes, camera_array(shot.camera), 161, 121, 0.3,
                                    warp=warp)
    known = np.isfinite(constant)
    assert 0.05 < known.mean() < 1.0
    full = render_raytrace(shot, 0.3, 16, 4, warp=warp, constant_regions=False)
    fast = render_raytrace(shot, 0.3, 16, 4, warp=warp)
    assert np.array_equal(fast[~known], full[~known])
    assert np.allclose(fast[known], full[known], rtol=0.0, atol=1e-6)


def test_unsupported_cases_trace_every_pixel():
    # A front stop (optical vignetting) and unknown aperture shapes are not decided here: every
    # pixel is traced, the image the same as with constant regions off.
    shot = make_shot([charuco(1300.0)], N=8.0, D=900.0)
    stop = (30.0, 5.0)
    full = render_raytrace(shot, 0.3, 16, 1, front_stop=stop, constant_regions=False)
    assert np.array_equal(render_raytrace(shot, 0.3, 16, 1, front_stop=stop), full)
    assert flat.shape_reach(("no-such-shape",)) is None
    structure, rasters, planes = scene_arrays(shot)
    assert np.isnan(flat.constant_pixels(structure, rasters, planes, camera_array(shot.camera), 97, 71, 0.3,
                                         ("no-such-shape",))).all()
