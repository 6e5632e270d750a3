"""The renderer against things it does not compute itself: second moments of a uniform disk,
the analytic edge-spread function, thin-lens geometry, conservation of light, Monte-Carlo
convergence."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from synth.convolve import render_convolve
from synth.raytrace import render_raytrace, thin_lens_ray
from synth.rendering import choose_method, render
from synth.scene import scene_from_dict


def make_scene(objects, *, f=50.0, N=2.8, D=2000.0, w=96, h=96, pitch=0.006, background=0.0, spp=64, seed=0,
               method="auto", supersampling=4):
    return scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D},
        "render": {"samples_per_pixel": spp, "seed": seed, "method": method, "supersampling": supersampling},
        "background": {"value": background},
        "object": objects,
    })


def coc_px(f, N, D, d, pitch):
    """The course's CoC formula written out here: A s |1/D - 1/d| / p."""
    s = 1.0 / (1.0 / f - 1.0 / D)
    return (f / N) * s * abs(1.0 / D - 1.0 / d) / pitch


@pytest.mark.parametrize("N, d", [(1.0, 2400.0), (2.8, 1600.0), (2.8, 3500.0), (8.0, 900.0), (16.0, 600.0),
                                  (16.0, 40000.0)])
def test_point_blur_diameter_from_second_moment(N, d):
    f, D, pitch = 50.0, 2000.0, 0.006
    expected = coc_px(f, N, D, d, pitch)
    s = 1.0 / (1.0 / f - 1.0 / D)
    # A tiny bright square (side a px on the sensor) on black.
    a_px = 6.0
    side_mm = a_px * pitch * d / s
    size = int(expected * 1.2) + 16
    scene = make_scene([{"target": "uniform", "value": 1.0, "distance_mm": d, "size_mm": [side_mm, side_mm]}],
                       f=f, N=N, D=D, w=size, h=size, pitch=pitch, method="raytrace")
    img = render_raytrace(scene.shots[0], 0.0, 1024, 1).astype(np.float64)
    # Light is conserved: the total equals the square's area in pixels (36 864 hits: 0.5% noise).
    assert img.sum() == pytest.approx(a_px**2, rel=0.02)
    yy, xx = np.mgrid[0:size, 0:size]
    m = img.sum()
    cx, cy = (img * xx).sum() / m, (img * yy).sum() / m
    var = 0.5 * ((img * (xx - cx) ** 2).sum() + (img * (yy - cy) ** 2).sum()) / m
    # Per-axis variance of a uniform disk of radius R is R^2/4; the square and the pixel
    # footprint add a^2/12 and 1/12.
    radius = 2.0 * math.sqrt(var - a_px**2 / 12 - 1 / 12)
    assert 2 * radius == pytest.approx(expected, rel=0.01)
    # The blur disk is centred on the chief ray of the square's centre (the image centre).
    assert cx == pytest.approx((size - 1) / 2, abs=0.05) and cy == pytest.approx((size - 1) / 2, abs=0.05)


def test_focus_at_infinity_blur():
    f, N, d, pitch = 35.0, 2.0, 3000.0, 0.005
    expected = (f / N) * f / d / pitch  # A f / d for focus at infinity
    a_px = 6.0
    side = a_px * pitch * d / f
    size = int(expected * 1.2) + 16
    scene = make_scene([{"target": "uniform", "value": 1.0, "distance_mm": d, "size_mm": [side, side]}],
                       f=f, N=N, D="inf", w=size, h=size, pitch=pitch, method="raytrace")
    img = render_raytrace(scene.shots[0], 0.0, 1024, 2).astype(np.float64)
    yy, xx = np.mgrid[0:size, 0:size]
    m = img.sum()
    cx, cy = (img * xx).sum() / m, (img * yy).sum() / m
    var = 0.5 * ((img * (xx - cx) ** 2).sum() + (img * (yy - cy) ** 2).sum()) / m
    assert 2 * 2 * math.sqrt(var - a_px**2 / 12 - 1 / 12) == pytest.approx(expected, rel=0.01)


def test_all_rays_of_a_pixel_meet_on_the_plane_of_focus():
    rng = np.random.default_rng(3)
    f, D, pitch = 50.0, 1500.0, 0.004
    s = 1.0 / (1.0 / f - 1.0 / D)
    with jax.enable_x64(True):  # the kernel runs in float32; check the geometry itself exactly
        cam = jnp.asarray([99.5, 49.5, pitch / s, 1.0 / D, f / 2.0], jnp.float64)
        lx, ly = rng.uniform(-12, 12, 500), rng.uniform(-12, 12, 500)
        rays = {p: thin_lens_ray(p[0], p[1], lx, ly, cam) for p in [(0.0, 0.0), (37.25, 80.5), (199.0, 99.0)]}
        centre = thin_lens_ray(99.5, 49.5, 0.0, 0.0, cam)
    for (px, py), (dx, dy) in rays.items():
        x_at_focus = lx + D * np.asarray(dx)
        y_at_focus = ly + D * np.asarray(dy)
        assert np.ptp(x_at_focus) < 1e-9 and np.ptp(y_at_focus) < 1e-9
        # ... on the pixel's chief ray, which passes through the lens centre.
        assert x_at_focus[0] == pytest.approx((px - 99.5) * pitch * D / s, abs=1e-9)
    # The lens centre's ray from the principal point is the optical axis.
    assert float(centre[0]) == 0.0 and float(centre[1]) == 0.0


def test_in_focus_plane_is_as_sharp_as_a_pinhole():
    board = {"target": "checkerboard", "squares": [6, 4], "square_mm": 10.0, "distance_mm": 1000.0}
    wide = make_scene([board], N=1.4, D=1000.0, w=160, h=120, background=0.3)
    pinhole = make_scene([board], N=5000.0, D=1000.0, w=160, h=120, background=0.3)
    a = render_raytrace(wide.shots[0], 0.3, 64, 0)
    b = render_raytrace(pinhole.shots[0], 0.3, 64, 0)
    # Same pixel samples (same seed), only the aperture differs: identical up to float32 rounding.
    assert np.max(np.abs(a - b)) < 1e-4
    # While out of focus the same board is clearly blurred.
    c = render_raytrace(make_scene([board], N=1.4, D=700.0, w=160, h=120, background=0.3).shots[0], 0.3, 64, 0)
    assert np.max(np.abs(a - c)) > 0.2


def test_defocus_preserves_mean_brightness_of_uniform_region():
    plane = {"target": "uniform", "value": 0.6, "distance_mm": 800.0, "size_mm": [2000.0, 2000.0]}
    img = render_raytrace(make_scene([plane], N=1.0, D=3000.0, w=64, h=48).shots[0], 0.0, 16, 0)
    np.testing.assert_allclose(img, 0.6, atol=1e-6)


def test_image_scale_follows_sensor_distance_not_focal_length():
    # Macro: f = 50 mm focused at 200 mm puts the sensor at s = 66.7 mm (not 50 mm).
    f, d, pitch, width_mm = 50.0, 200.0, 0.01, 40.0
    s = 1.0 / (1.0 / f - 1.0 / d)
    scene = make_scene([{"target": "uniform", "value": 1.0, "distance_mm": d, "size_mm": [width_mm, width_mm]}],
                       f=f, N=4.0, D=d, w=1500, h=9, pitch=pitch, method="raytrace")
    row = render_raytrace(scene.shots[0], 0.0, 16, 0)[4].astype(np.float64)
    measured_px = row.sum()  # each pixel is the covered fraction; the sum is the width in pixels
    assert measured_px == pytest.approx(width_mm * s / d / pitch, rel=2e-3)
    assert abs(measured_px - width_mm * f / d / pitch) > 100


def disk_esf(t, radius):
    """Edge-spread function of a uniform disk (fraction of the disk with x < t)."""
    x = np.clip(t / radius, -1.0, 1.0)
    return 0.5 + (x * np.sqrt(1 - x * x) + np.arcsin(x)) / np.pi


@pytest.mark.parametrize("method, N, d", [("convolve", 2.0, 1400.0), ("raytrace", 2.0, 1400.0),
                                          ("raytrace", 8.0, 1960.0)])  # the last: CoC 0.55 px
def test_edge_profile_matches_analytic_disk_esf(method, N, d):
    f, D, pitch = 50.0, 2000.0, 0.006
    c = coc_px(f, N, D, d, pitch)
    s = 1.0 / (1.0 / f - 1.0 / D)
    mm_per_px = pitch * d / s
    # A bright half-plane: a uniform rectangle whose left edge sits at x = 10.3 px right of centre.
    edge_px = 10.3
    width = 1000 * mm_per_px
    obj = {"target": "uniform", "value": 1.0, "distance_mm": d, "size_mm": [width, 400 * mm_per_px],
           "offset_mm": [edge_px * mm_per_px + width / 2, 0.0]}
    W, H = 160, 24
    scene = make_scene([obj], f=f, N=N, D=D, w=W, h=H, pitch=pitch, method=method)
    shot = scene.shots[0]
    img = render_convolve(shot, 0.0, 4) if method == "convolve" else render_raytrace(shot, 0.0, 1024, 5)
    profile = img[4:-4].mean(axis=0).astype(np.float64)
    u = np.arange(W) - (W - 1) / 2
    fine = (np.arange(64) + 0.5) / 64 - 0.5
    expected = disk_esf(u[:, None] + fine[None, :] - edge_px, c / 2).mean(axis=1)  # with pixel integration
    tol = 5e-4 if method == "convolve" else 4e-3  # raytrace: Monte-Carlo noise at 1024 spp, 16 rows
    assert np.max(np.abs(profile - expected)) < tol


def test_convolve_agrees_with_converged_raytrace_on_a_charuco_board():
    # The exact area sampling of boards makes convolve agree with 4096-spp ray tracing to the
    # ray tracer's own noise.
    scene = make_scene([{"target": "charuco", "squares": [5, 4], "square_mm": 6.0, "marker_mm": 4.5,
                         "dictionary": "DICT_4X4_50", "distance_mm": 1100.0, "offset_mm": [1.0, -0.7]}],
                       N=2.0, D=1500.0, w=96, h=80, background=0.3)
    shot = scene.shots[0]
    runs = [render_raytrace(shot, 0.3, 1024, k).astype(np.float64) for k in range(4)]
    reference = np.mean(runs, axis=0)
    noise = np.std([r - reference for r in runs]) * math.sqrt(4 / 3) / 2
    diff = render_convolve(shot, 0.3, 4) - reference
    assert np.sqrt(np.mean(diff**2)) < 1.3 * noise + 1e-4
    assert abs(diff.mean()) < 1e-4


def test_raytrace_converges_to_convolve_like_inverse_sqrt_spp():
    board = {"target": "checkerboard", "squares": [8, 6], "square_mm": 12.0, "distance_mm": 1300.0}
    scene = make_scene([board], N=2.0, D=2000.0, w=128, h=96, background=0.3, supersampling=8)
    shot = scene.shots[0]
    reference = render_convolve(shot, 0.3, 8).astype(np.float64)
    errors = {spp: np.sqrt(np.mean((render_raytrace(shot, 0.3, spp, 7) - reference) ** 2)) for spp in (16, 256)}
    ratio = errors[16] / errors[256]
    # At least as fast as 1/sqrt(spp) (sqrt(256/16) = 4); stratified sampling does somewhat better.
    assert ratio > 3.5
    assert errors[256] < 0.01
    # No bias: the mean difference is far below the noise.
    assert abs(np.mean(render_raytrace(shot, 0.3, 256, 8) - reference)) < 5e-4


def test_auto_method_choice_and_reason():
    flat = make_scene([{"target": "checkerboard", "squares": [4, 4], "square_mm": 5.0, "distance_mm": 1000.0}])
    method, exact, why = choose_method(flat.shots[0], "auto")
    assert method == "convolve" and exact and "fronto-parallel" in why
    tilted = make_scene([{"target": "checkerboard", "squares": [4, 4], "square_mm": 5.0, "distance_mm": 1000.0,
                          "tilt_deg": [0.0, 30.0]}])
    method, exact, why = choose_method(tilted.shots[0], "auto")
    assert method == "raytrace" and "tilted" in why
    sharp = make_scene([{"target": "checkerboard", "squares": [4, 4], "square_mm": 5.0, "distance_mm": 1990.0}],
                       D=2000.0)
    method, exact, why = choose_method(sharp.shots[0], "auto")
    assert method == "raytrace" and "less than" in why
    overlapping = make_scene([
        {"id": "back", "target": "checkerboard", "squares": [4, 4], "square_mm": 5.0, "distance_mm": 1000.0},
        {"id": "front", "target": "uniform", "size_mm": [5.0, 5.0], "distance_mm": 700.0}])
    method, exact, why = choose_method(overlapping.shots[0], "auto")
    assert method == "raytrace" and "overlap" in why
    assert choose_method(overlapping.shots[0], "convolve")[1] is False


def test_occlusion_nearest_surface_wins():
    # In focus, a small near square in front of a far wall: its pixels show only the square.
    scene = make_scene([
        {"id": "wall", "target": "uniform", "value": 0.2, "size_mm": [500.0, 500.0], "distance_mm": 2000.0},
        {"id": "card", "target": "uniform", "value": 0.9, "size_mm": [2.0, 2.0], "distance_mm": 1000.0}],
        N=16.0, D=1000.0, w=64, h=64, method="raytrace")
    result = render(scene)
    img = next(iter(result.images.values()))
    assert img[32, 32] == pytest.approx(0.9, abs=1e-6)
    assert img[2, 2] == pytest.approx(0.2, abs=1e-6)
    depth = next(iter(result.maps.values()))["depth_mm"]
    assert depth[32, 32] == pytest.approx(1000.0) and depth[2, 2] == pytest.approx(2000.0)


def test_depth_map_covers_each_target_where_opencv_projects_it():
    # Tilted targets, one reaching past the frame, one far off to the side (partly visible), one
    # beyond the frame altogether: the depth map is finite exactly inside the outline OpenCV's
    # projection of each target's corners gives, and its value there is the distance along the
    # chief ray to the target's plane, solved for pixel by pixel here.
    import cv2

    from synth.truth import chief_ray_depth

    objects = [
        {"id": "tilted", "target": "uniform", "value": 0.5, "size_mm": [60.0, 40.0], "distance_mm": 1000.0,
         "tilt_deg": [30.0, -20.0], "offset_mm": [-20.0, 10.0]},
        {"id": "edge", "target": "uniform", "value": 0.5, "size_mm": [80.0, 80.0], "distance_mm": 1500.0,
         "tilt_deg": [-15.0, 40.0], "offset_mm": [110.0, -60.0]},
        {"id": "outside", "target": "uniform", "value": 0.5, "size_mm": [10.0, 10.0], "distance_mm": 800.0,
         "offset_mm": [500.0, 0.0]},
    ]
    shot = make_scene(objects, w=160, h=120).shots[0]
    cam = shot.camera
    depth = chief_ray_depth(shot)
    fpx, (cx, cy) = cam.focal_length_px, cam.principal_point_px
    K = np.array([[fpx, 0.0, cx], [0.0, fpx, cy], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:cam.height_px, 0:cam.width_px]
    expected = np.full(depth.shape, np.inf)
    for o in shot.objects:
        w, h = o.target.size_mm
        R, t = o.pose.R_cam_target, o.pose.t_cam_target
        outline = np.array([[-w / 2, -h / 2, 0.0], [w / 2, -h / 2, 0.0], [w / 2, h / 2, 0.0], [-w / 2, h / 2, 0.0]])
        px = cv2.projectPoints(outline, cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0].reshape(-1, 1, 2)
        inside = np.array([cv2.pointPolygonTest(px.astype(np.float32), (float(x), float(y)), True)
                           for x, y in zip(u.ravel(), v.ravel())]).reshape(depth.shape)
        ray = np.stack([(u - cx) / fpx, (v - cy) / fpx, np.ones_like(u, float)], axis=-1)
        z = (t @ R[:, 2]) / (ray @ R[:, 2])  # the plane n . (X - t) = 0 along the ray (X = z ray)
        sure = inside > 1e-6  # (pixel centres on the outline itself: either way)
        expected = np.where(sure & (z < expected), z, expected)
        assert np.all(np.isfinite(depth[sure]))
        if o.target.id == "outside":
            assert not sure.any()
    near_outline = ~np.isfinite(expected) & np.isfinite(depth)
    assert near_outline.sum() < 0.01 * depth.size  # only pixel centres within rounding of an outline
    both = np.isfinite(expected) & np.isfinite(depth)
    assert both.sum() > 0.1 * depth.size
    assert np.allclose(depth[both], expected[both], rtol=1e-9)


def test_deterministic_for_a_seed():
    board = {"target": "checkerboard", "squares": [4, 3], "square_mm": 10.0, "distance_mm": 900.0,
             "tilt_deg": [10.0, 0.0]}
    scene = make_scene([board], N=2.0, D=1500.0, w=64, h=48, background=0.3)
    a = render(scene, seed=5).images["shot_000.png"]
    b = render(scene, seed=5).images["shot_000.png"]
    c = render(scene, seed=6).images["shot_000.png"]
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_sobol_points_are_scipys():
    # The renderer's own 4-D Sobol generator (it avoids importing scipy.stats) against SciPy's.
    from scipy.stats import qmc

    from synth.raytrace import sobol_16bit

    for m in range(17):
        reference = np.floor(qmc.Sobol(4, scramble=False).random_base2(m) * 65536).astype(np.uint32)
        assert np.array_equal(sobol_16bit(m), reference), m


@pytest.mark.parametrize("spp", [1, 4, 12, 16, 36, 64, 256, 1024])
def test_a_pixels_samples_are_the_sobol_points_one_per_cell(spp):
    # Put back where the kernel puts them (sample k in cell (k % n, k // n) of an n x n grid where
    # spp = n^2), a pixel's samples are the first spp Sobol points of SciPy, whole 4-D points (so
    # pixel and lens positions keep their joint stratification), each in its own pixel cell.
    from scipy.stats import qmc

    from synth.raytrace import sample_table

    table = sample_table(spp).astype(np.float64) / 65536.0
    n = math.isqrt(spp)
    sobol = qmc.Sobol(4, scramble=False).random_base2(max(0, math.ceil(math.log2(spp))))[:spp]
    if n * n == spp and spp & (spp - 1) == 0:
        k = np.arange(spp)
        table[:, 0] = (k % n + table[:, 0]) / n
        table[:, 1] = (k // n + table[:, 1]) / n
        assert sorted(map(tuple, np.round(table * 65536))) == sorted(map(tuple, np.floor(sobol * 65536)))
        cells = np.floor(table[:, 0] * n) + n * np.floor(table[:, 1] * n)
        assert np.array_equal(np.sort(cells), np.arange(spp))
    else:  # the samples as they are (a square spp not a power of 2 only jitters them within their cells)
        assert np.array_equal(table, np.floor(sobol * 65536) / 65536.0)


def test_randomised_quasi_monte_carlo_beats_independent_samples():
    # Each pixel's samples are a digitally shifted Sobol set: unbiased (the mean over seeds meets
    # the exact render) and, on a blurred board, with far less error than independent uniform
    # samples would give: their RMS error is the pixels' own spread of radiance over sqrt(spp),
    # estimated here from the same renderer at 1 spp (one sample per pixel, uniform: the shift).
    board = {"target": "checkerboard", "squares": [8, 6], "square_mm": 12.0, "distance_mm": 1300.0}
    scene = make_scene([board], N=2.0, D=2000.0, w=128, h=96, background=0.3, supersampling=8)
    shot = scene.shots[0]
    reference = render_convolve(shot, 0.3, 8).astype(np.float64)
    single = np.array([render_raytrace(shot, 0.3, 1, seed) for seed in range(16)], np.float64)
    independent_rms_64 = math.sqrt(np.mean((single - reference) ** 2) / 64)
    runs = np.array([render_raytrace(shot, 0.3, 64, seed) for seed in range(4)], np.float64)
    rms_64 = math.sqrt(np.mean((runs - reference) ** 2))
    assert rms_64 < 0.4 * independent_rms_64  # (0.32; hashed jitter with permuted lens strata: 0.41)
    assert abs(np.mean(runs - reference)) < 2e-4


def test_raytrace_is_independent_of_tiling(monkeypatch):
    # The same image whatever the tiles (each pixel's samples depend on the seed and the pixel
    # alone): one tile of the whole image, tiles of 64 and of 16 pixels, each dispatched ahead.
    import synth.raytrace as rt

    board = {"target": "checkerboard", "squares": [4, 3], "square_mm": 10.0, "distance_mm": 900.0,
             "tilt_deg": [10.0, 0.0]}
    shot = make_scene([board], N=2.0, D=1500.0, w=64, h=48, background=0.3).shots[0]
    images = []
    for tile in (1 << 20, 64 * 16, 256):
        monkeypatch.setattr(rt, "TILE_SAMPLES", tile)
        images.append(rt.render_raytrace(shot, 0.3, 16, 3, fine=4))
    for image, fine in images[1:]:
        assert np.array_equal(image, images[0][0])
        # (the cells' means are summed in another order in another tile shape: float32)
        assert np.allclose(fine, images[0][1], rtol=0.0, atol=1e-6)
