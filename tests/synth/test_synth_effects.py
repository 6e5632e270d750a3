"""synth's effects against what they do not compute themselves: the shape of bokeh measured
from the image, the Airy pattern's first dark ring, the photon-transfer (EMVA 1288) mean and
variance of flat fields, the cos^4 law and a brute-force pupil overlap, OpenCV's own
distortion model, rawpy's DNG decoder, and per-channel best focus found in the image. And that
an effect not called for runs no code, draws no random numbers and changes nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lensfit.errors import InputError, SpecError
from synth.rendering import render
from synth.scene import scene_from_dict


def scene(objects, *, effects=("defocus",), f=50.0, N=8.0, D=2000.0, w=96, h=96, pitch=0.006, background=0.0,
          spp=64, seed=0, method="auto", aperture="circle", **tables):
    data = {
        "camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D, "aperture": aperture},
        "render": {"samples_per_pixel": spp, "seed": seed, "method": method, "effects": list(effects)},
        "background": {"value": background},
        "object": objects,
    }
    data.update(tables)
    return scene_from_dict(data)


def sensor_distance(f, D):
    return 1.0 / (1.0 / f - 1.0 / D)


def point(d_mm, f, D, pitch, side_px=0.25):
    """A tiny bright square (side ``side_px`` on the sensor) on the axis at depth d."""
    side = side_px * pitch * d_mm / sensor_distance(f, D)
    return {"target": "uniform", "value": 1.0, "distance_mm": d_mm, "size_mm": [side, side]}


def the_image(result):
    return next(iter(result.images.values())).astype(np.float64)


# --------------------------------------------------------------------------- aperture shapes


def boundary_radius(img, n_angles=720):
    """Radius of the spot's half-maximum boundary along each direction from its centroid."""
    from scipy.ndimage import map_coordinates

    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    m = img.sum()
    cx, cy = (img * xx).sum() / m, (img * yy).sum() / m
    level = 0.5 * np.percentile(img[img > 0.5 * img.max()], 50)
    radii = np.arange(0, min(img.shape) / 2 - 1, 0.05)
    theta = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    out = []
    for t in theta:
        vals = map_coordinates(img, [cy - radii * np.sin(t), cx + radii * np.cos(t)], order=1)
        out.append(radii[np.argmax(vals < level)])
    return theta, np.array(out)


@pytest.mark.parametrize("method, blades, rotation, d", [("convolve", 6, 0.0, 1000.0), ("convolve", 5, 20.0, 1000.0),
                                                         ("convolve", 5, 20.0, 8000.0), ("raytrace", 7, 10.0, 1000.0),
                                                         ("raytrace", 5, 20.0, 8000.0), ("convolve", 9, 0.0, 8000.0)])
def test_polygon_bokeh_has_the_blade_count_and_rotation(method, blades, rotation, d):
    """Behind the plane of focus the bokeh has the aperture's orientation; in front of it the
    rays have not crossed yet, and the stored (re-inverted) image shows it turned by 180 degrees."""
    from scipy.ndimage import uniform_filter

    f, D, pitch = 50.0, 2000.0, 0.006
    # A ray tracer sees a point only through the rays that hit it: a 2 px patch, many rays, and
    # a 3 x 3 box filter keep the Monte-Carlo noise of the spot near 5 %.
    side = 2.0 if method == "raytrace" else 0.25
    sc = scene([point(d, f, D, pitch, side_px=side)], effects=("defocus", "aperture"), f=f, N=4.0, D=D, w=81, h=81,
               pitch=pitch, method=method, spp=16384,
               aperture={"shape": "polygon", "blades": blades, "rotation_deg": rotation})
    img = the_image(render(sc))
    if method == "raytrace":
        img = uniform_filter(img, 3)
    theta, r = boundary_radius(img)
    spectrum = np.abs(np.fft.rfft(r - r.mean()))
    assert int(np.argmax(spectrum[1:40])) + 1 == blades  # the dominant harmonic of r(theta)
    # Vertices (radius maxima) sit at rotation + k 360/n, counter-clockwise in the image.
    phase = np.angle(np.fft.rfft(r)[blades])
    vertex_deg = math.degrees(-phase / blades) % (360 / blades)
    expected = (rotation + (180.0 if d < D else 0.0)) % (360 / blades)
    diff = (vertex_deg - expected + 180 / blades) % (360 / blades) - 180 / blades
    assert abs(diff) < 2.0
    # Circumscribed circle: the CoC formula's diameter, measured at the vertices.
    A = f / 4.0
    coc = A * sensor_distance(f, D) * abs(1 / D - 1 / d) / pitch
    assert 2 * r.max() == pytest.approx(coc, rel=0.04)


@pytest.mark.parametrize("method, squeeze", [("convolve", 1.33), ("convolve", 2.0), ("raytrace", 1.5),
                                             ("convolve", 0.7)])
def test_anamorphic_bokeh_has_the_squeeze_ratio(method, squeeze):
    f, D, pitch, d = 50.0, 2000.0, 0.006, 1000.0
    side = 2.0 if method == "raytrace" else 0.25  # moments below allow for the patch's a^2/12
    sc = scene([point(d, f, D, pitch, side_px=side)], effects=("defocus", "aperture"), f=f, N=4.0, D=D, w=81, h=81,
               pitch=pitch, method=method, spp=16384, aperture={"shape": "anamorphic", "squeeze": squeeze})
    img = the_image(render(sc))
    yy, xx = np.mgrid[0:81, 0:81]
    m = img.sum()
    cx, cy = (img * xx).sum() / m, (img * yy).sum() / m
    # Second moments of a uniform ellipse are a^2/4 and b^2/4 (plus the pixel's 1/12).
    vx = (img * (xx - cx) ** 2).sum() / m - 1 / 12 - side**2 / 12
    vy = (img * (yy - cy) ** 2).sum() / m - 1 / 12 - side**2 / 12
    assert math.sqrt(vy / vx) == pytest.approx(squeeze, rel=0.02)
    coc = f / 4.0 * sensor_distance(f, D) * abs(1 / D - 1 / d) / pitch
    assert 4 * math.sqrt(vy) == pytest.approx(coc, rel=0.02)


# --------------------------------------------------------------------------- diffraction


def first_minimum_px(img, expected):
    """Radius of the first minimum of a spot centred on pixel (40, 40): coarse search on a 0.5 px
    azimuthal average, then a parabola fitted to every pixel within 1.5 px of it."""
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    r = np.hypot(xx - 40, yy - 40).ravel()
    values = img.ravel()
    centres = np.arange(0.5 * expected, 1.5 * expected, 0.5)
    coarse = [values[np.abs(r - c) < 0.5].mean() for c in centres]
    r0 = centres[int(np.argmin(coarse))]
    near = np.abs(r - r0) < 1.5
    a, b, _ = np.polyfit(r[near], values[near], 2)
    return -b / (2 * a)


def pixel_integrated_airy(airy_px, size=81, k=16):
    """The Airy intensity (2 J1(x) / x)^2, x = pi r / airy_px, centred on pixel (40, 40) and
    averaged over each pixel's area (k x k points): what a sensor records of a point."""
    from scipy.special import j1

    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    out = np.zeros((size, size))
    for ox in (np.arange(k) + 0.5) / k - 0.5:
        for oy in (np.arange(k) + 0.5) / k - 0.5:
            x = np.maximum(np.pi * np.hypot(xx - 40 + ox, yy - 40 + oy) / airy_px, 1e-9)
            out += (2 * j1(x) / x) ** 2
    return out / k**2


@pytest.mark.parametrize("N, wavelength, D", [(32.0, 550.0, 1e6), (22.0, 650.0, 1e6), (16.0, 450.0, 150.0)])
def test_airy_first_dark_ring_at_1_22_lambda_N(N, wavelength, D):
    f, pitch = 50.0, 0.0015
    sc = scene([point(D, f, D, pitch, side_px=0.2)], effects=("defocus", "diffraction"), f=f, N=N, D=D, w=81, h=81,
               pitch=pitch, method="convolve", diffraction={"wavelength_nm": wavelength})
    img = the_image(render(sc))
    N_w = N * sensor_distance(f, D) / f  # image-side f-number: the sensor is at s, not f
    airy_px = wavelength * 1e-6 * N_w / pitch
    expected = 1.22 * airy_px
    found = first_minimum_px(img, expected)
    # The pixels integrate the pattern, which moves the minimum they show outward by 1-3 %:
    # against the closed-form pattern averaged over each pixel, found the same way, within 0.5 %.
    assert found == pytest.approx(first_minimum_px(pixel_integrated_airy(airy_px), expected), rel=0.005)
    assert found == pytest.approx(expected, rel=0.04)


# --------------------------------------------------------------------------- exposure and noise

FLAT = {"target": "uniform", "value": 0.5, "distance_mm": 2000.0, "size_mm": [2000.0, 2000.0]}


def flat_field(iso, shutter, *, noise=True, preset="aps-c-24mp", seed=0, w=200, h=200, luminance=1000.0,
               read_noise=True):
    effects = ("defocus", "exposure", "noise") if noise else ("defocus", "exposure")
    tables = {"noise": {"read": read_noise}} if noise else {}
    sc = scene([FLAT], effects=effects, w=w, h=h, method="convolve", seed=seed,
               exposure={"shutter_s": shutter, "iso": iso, "luminance_cd_m2": luminance}, sensor={"preset": preset},
               **tables)
    res = render(sc)
    return next(iter(res.raw.values())).astype(np.float64), res


PRESET = {"full_well_e": 35000.0, "read_noise_e": 2.5, "dark_current_e_per_s": 0.5, "bits": 14, "black": 600,
          "base_iso": 100.0}  # data_specs/sensor_presets.toml, aps-c-24mp, copied


def photon_transfer(iso, shutter, value=0.5, N=8.0, f=50.0, D=2000.0, L=1000.0, T=0.9):
    """EMVA 1288 linear model with ISO 12232 saturation speed, written out independently."""
    p = PRESET
    N_w = N * sensor_distance(f, D) / f
    H = value * math.pi / 4 * T * L * shutter / N_w**2           # lux s
    mu = H / (78.0 / p["base_iso"]) * p["full_well_e"] + p["dark_current_e_per_s"] * shutter
    white = 2 ** p["bits"] - 1
    g = (white - p["black"]) / p["full_well_e"] * iso / p["base_iso"]
    return p["black"] + g * mu, g * g * (mu + p["read_noise_e"] ** 2) + 1 / 12, g, mu


@pytest.mark.parametrize("iso, shutter", [(100, 0.045), (400, 0.011), (1600, 0.0028), (6400, 0.0007)])
def test_flat_field_mean_and_variance_follow_the_photon_transfer_model(iso, shutter):
    raw, res = flat_field(iso, shutter)
    mean, var, g, mu = photon_transfer(iso, shutter)
    assert raw.mean() == pytest.approx(mean, rel=2e-3, abs=0.5)
    # 40 000 pixels: the variance's standard error is about 0.7 %.
    assert raw.var() == pytest.approx(var, rel=0.04)
    info = res.truth["images"][0]["exposure"]
    assert info["gain_dn_per_e"] == pytest.approx(g, rel=1e-12)


def test_full_well_clips_to_the_white_level_and_iso_clips_before_it():
    # 10x the exposure that fills the well at base ISO: every pixel holds the full well. Read
    # noise comes after the well (so a saturated pixel may read a little below white).
    raw, _ = flat_field(100, 5.0, read_noise=False)
    assert np.all(raw == 2**14 - 1)
    raw, _ = flat_field(100, 5.0)
    g = (2**14 - 1 - PRESET["black"]) / PRESET["full_well_e"]
    assert raw.max() == 2**14 - 1 and raw.min() > 2**14 - 1 - 6 * g * PRESET["read_noise_e"]
    # At ISO 800 the white level is reached at 1/8 of the full well: a signal of 1/4 clips.
    mean, _, g, mu = photon_transfer(800, 0.037)
    assert mu < PRESET["full_well_e"] / 3 and mean > 2**14 - 1
    raw, _ = flat_field(800, 0.037)
    assert np.all(raw == 2**14 - 1)


def test_without_noise_a_flat_field_is_the_rounded_mean_and_steps_are_whole_dn():
    for iso, shutter in [(100, 0.04), (1600, 0.0023)]:
        raw, _ = flat_field(iso, shutter, noise=False)
        mean, _, _, _ = photon_transfer(iso, shutter)
        assert np.all(raw == np.rint(mean))
    # A 12-bit sensor: values on the integer grid up to 4095 (file is 16-bit).
    raw, res = flat_field(200, 0.03, preset="micro-four-thirds-20mp")
    assert 256 < raw.min() and raw.max() < 4095
    assert raw.max() <= 4095 and np.all(raw == np.rint(raw))
    assert res.levels[next(iter(res.levels))] == {"black_level": 256, "white_level": 4095}


def test_noise_is_deterministic_for_a_seed_and_differs_between_seeds():
    a, _ = flat_field(400, 0.01, seed=3, w=64, h=64)
    b, _ = flat_field(400, 0.01, seed=3, w=64, h=64)
    c, _ = flat_field(400, 0.01, seed=4, w=64, h=64)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_stack_with_sensor_levels_reads_back_linear(tmp_path):
    from lensfit.io.stack import load_stack
    from synth.stack import write_stack

    raw, res = flat_field(100, 0.04, noise=False, w=48, h=32)
    write_stack(res, tmp_path / "s")
    stack = load_stack(tmp_path / "s")
    mean, _, _, _ = photon_transfer(100, 0.04)
    expected = (np.rint(mean) - PRESET["black"]) / (2**14 - 1 - PRESET["black"])
    assert np.allclose(stack.read(0), expected, atol=1e-12)


# --------------------------------------------------------------------------- vignetting


def test_natural_vignetting_follows_cos4():
    f, pitch, w, h = 8.0, 0.05, 160, 120  # corner field angle 32 degrees
    big = {"target": "uniform", "value": 0.8, "distance_mm": 1000.0, "size_mm": [5000.0, 5000.0]}
    sc = scene([big], effects=("defocus", "vignetting"), f=f, N=4.0, D=1000.0, w=w, h=h, pitch=pitch,
               method="convolve")
    img = the_image(render(sc))
    s = sensor_distance(f, 1000.0)
    yy, xx = np.mgrid[0:h, 0:w]
    theta = np.arctan(np.hypot(xx - (w - 1) / 2, yy - (h - 1) / 2) * pitch / s)
    assert np.allclose(img, 0.8 * np.cos(theta) ** 4, atol=2e-6)
    assert img[0, 0] < 0.8 * 0.55


def test_optical_vignetting_matches_the_pupil_overlap():
    """Cat's eye: the fraction of the pupil passing a front stop, against brute-force sampling."""
    f, N, D, pitch, w, h = 35.0, 2.0, 1000.0, 0.1, 64, 48
    L, B = 60.0, 18.0  # clear on the axis, clipped towards the corners
    big = {"target": "uniform", "value": 1.0, "distance_mm": D, "size_mm": [5000.0, 5000.0]}
    sc = scene([big], effects=("defocus", "vignetting"), f=f, N=N, D=D, w=w, h=h, pitch=pitch, spp=1024,
               vignetting={"natural": False, "front_stop_distance_mm": L, "front_stop_diameter_mm": B})
    res = render(sc)
    assert res.truth["images"][0]["method"] == "raytrace"
    img = the_image(res)
    s = sensor_distance(f, D)
    A = f / N
    # Brute force: a fine grid over the pupil; a ray from lens point l towards the in-focus
    # point of sensor point x passes z = L at l + L (x D/s - l)/D.
    g = np.linspace(-A / 2, A / 2, 801)
    lx, ly = np.meshgrid(g, g)
    pupil = lx**2 + ly**2 <= (A / 2) ** 2
    for (u, v) in [(32, 24), (50, 24), (63, 47), (5, 40), (63, 0)]:
        x = (u - (w - 1) / 2) * pitch
        y = (v - (h - 1) / 2) * pitch
        bx = lx + L * (x * D / s - lx) / D
        by = ly + L * (y * D / s - ly) / D
        clear = (pupil & (bx**2 + by**2 <= (B / 2) ** 2)).sum() / pupil.sum()
        block = img[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2].mean()  # 9 pixels x 1024 rays
        assert block == pytest.approx(clear, abs=0.01)
    assert img[24, 32] == pytest.approx(1.0, abs=1e-6) and img[0, 0] < 0.75


def test_optical_vignetting_refuses_convolve():
    big = {"target": "uniform", "value": 1.0, "distance_mm": 1000.0, "size_mm": [5000.0, 5000.0]}
    sc = scene([big], effects=("defocus", "vignetting"), method="convolve",
               vignetting={"front_stop_distance_mm": 30.0, "front_stop_diameter_mm": 20.0})
    with pytest.raises(InputError, match="ray tracing"):
        render(sc)


# --------------------------------------------------------------------------- distortion


@pytest.mark.parametrize("method, coeffs", [("convolve", {"k1": -0.25, "k2": 0.05}),
                                            ("convolve", {"k1": 0.15, "p1": 0.004, "p2": -0.003}),
                                            ("raytrace", {"k1": -0.25, "k2": 0.05, "p1": 0.003})])
def test_distorted_checkerboard_corners_match_opencv_projection(method, coeffs):
    """convolve resamples its render; the ray tracer traces each sample's undistorted ray."""
    import cv2

    # wide angle (52 x 40 degrees), corners blurred over ~4 px
    f, D, pitch, w, h, z = 16.0, 1e6, 0.05, 320, 240, 1000.0
    board = {"target": "checkerboard", "squares": [10, 8], "square_mm": 75.0, "distance_mm": z}
    sc = scene([board], effects=("defocus", "distortion"), f=f, N=1.4, D=D, w=w, h=h, pitch=pitch, background=0.5,
               method=method, spp=1024, distortion=coeffs)
    res = render(sc)
    img = the_image(res)
    found, corners = cv2.findChessboardCornersSB(np.round(img * 255).astype(np.uint8), (9, 7),
                                                 flags=cv2.CALIB_CB_ACCURACY)
    assert found
    # cornerSubPix on the float image (findChessboardCornersSB alone is good to ~0.15 px)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    detected = cv2.cornerSubPix(img.astype(np.float32), corners, (5, 5), (-1, -1), criteria).reshape(-1, 2)
    # OpenCV's own model projects the true inner corners.
    s = sensor_distance(f, D)
    K = np.array([[s / pitch, 0, (w - 1) / 2], [0, s / pitch, (h - 1) / 2], [0, 0, 1]])
    ij = np.array([(i, j) for j in range(1, 8) for i in range(1, 10)], np.float64)
    pts = np.column_stack([(ij[:, 0] - 5) * 75.0, (ij[:, 1] - 4) * 75.0, np.zeros(len(ij))])
    dist = np.array([coeffs.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
    projected, _ = cv2.projectPoints(pts, np.zeros(3), np.array([0, 0, z], np.float64), K, dist)
    projected = projected.reshape(-1, 2)
    nearest = np.min(np.linalg.norm(projected[:, None] - detected[None], axis=-1), axis=1)
    assert np.max(nearest) < 0.06
    # the distortion is large enough to matter: the pinhole corners are pixels away
    pinhole, _ = cv2.projectPoints(pts, np.zeros(3), np.array([0, 0, z], np.float64), K, np.zeros(5))
    assert np.max(np.linalg.norm(pinhole.reshape(-1, 2) - projected, axis=1)) > 3.0
    assert res.truth["effect_parameters"]["distortion"]["opencv_dist_coeffs"] == dist.tolist()
    # truth: corners where the image shows them, and the depth map of the distorted image
    outer = np.array([[-375.0, -300.0, 0.0], [375.0, -300.0, 0.0], [375.0, 300.0, 0.0], [-375.0, 300.0, 0.0]])
    corners, _ = cv2.projectPoints(outer, np.zeros(3), np.array([0, 0, z], np.float64), K, dist)
    target = res.truth["images"][0]["targets"][0]
    assert np.allclose(target["corners_px_distorted"], corners.reshape(-1, 2), atol=1e-6)
    depth = res.maps[res.truth["images"][0]["maps"]]["depth_mm"]
    row = h // 2
    left_edge = cv2.projectPoints(np.array([[-375.0, (row - (h - 1) / 2) * pitch * z / s, 0.0]]), np.zeros(3),
                                  np.array([0, 0, z], np.float64), K, dist)[0].reshape(2)[0]
    assert int(np.argmax(np.isfinite(depth[row]))) == math.ceil(left_edge)


# --------------------------------------------------------------------------- chromatic aberration


def test_longitudinal_ca_best_focus_per_channel_matches_the_model():
    """Each channel's blur of an edge, measured across depth, is least at 1/D_c = 1/f_c - 1/s."""
    f, N, D, pitch, w, h = 50.0, 8.0, 1000.0, 0.005, 96, 24
    shifts = [0.15, 0.0, -0.12]
    s = sensor_distance(f, D)
    depths = np.linspace(800.0, 1300.0, 11)
    shots, objects = [], []
    for k, z in enumerate(depths):
        # a bright half-plane whose right edge runs through the image centre
        half = 2000.0
        objects.append({"id": f"e{k}", "target": "uniform", "value": 1.0, "distance_mm": float(z),
                        "size_mm": [half, half], "offset_mm": [-half / 2, 0.0]})
        shots.append({"objects": [f"e{k}"]})
    data = {"camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
            "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D},
            "render": {"effects": ["defocus", "chromatic_aberration"], "method": "convolve"},
            "background": {"value": 0.0}, "object": objects, "shot": shots,
            "chromatic_aberration": {"focal_shift_mm": shifts}}
    res = render(scene_from_dict(data))
    images = list(res.images.values())
    assert images[0].shape == (h, w, 3)
    for c, df in enumerate(shifts):
        variances = []
        for img in images:
            profile = img[:, :, c].astype(np.float64).mean(axis=0)
            lsf = -np.diff(profile)
            x = np.arange(len(lsf))
            m = lsf.sum()
            mu = (lsf * x).sum() / m
            variances.append((lsf * (x - mu) ** 2).sum() / m)
        # variance = C^2/16 + const, C proportional to |1/z - 1/D_c|: a parabola in 1/z
        a, b, _ = np.polyfit(1.0 / depths, variances, 2)
        measured = 1.0 / (-b / (2 * a))
        expected = 1.0 / (1.0 / (f + df) - 1.0 / s)
        assert measured == pytest.approx(expected, rel=0.005)
    assert res.truth["images"][0]["chromatic_aberration"]["channel_focus_distance_mm"][0] == pytest.approx(
        1.0 / (1.0 / (f + shifts[0]) - 1.0 / s), rel=1e-12)


def test_lateral_ca_scales_each_channel_about_the_centre():
    f, D, pitch, w, h, z = 50.0, 2000.0, 0.006, 201, 201, 1500.0
    s = sensor_distance(f, D)
    off_px = 80.0
    spot = point(z, f, D, pitch, side_px=3.0)  # blurred over ~6 px
    spot["offset_mm"] = [off_px * pitch * z / s, 0.0]
    mags = [1.01, 1.0, 0.985]
    sc = scene([spot], effects=("defocus", "chromatic_aberration"), f=f, N=8.0, D=D, w=w, h=h, pitch=pitch,
               method="convolve", chromatic_aberration={"magnification": mags})
    img = the_image(render(sc))
    xx = np.arange(w)
    for c, m in enumerate(mags):
        ch = img[:, :, c]
        centroid = (ch.sum(axis=0) * xx).sum() / ch.sum()
        assert centroid - 100.0 == pytest.approx(off_px * m, abs=0.02)
        assert ch.sum() == pytest.approx(9.0, rel=2e-3)  # the spot's light is conserved


# --------------------------------------------------------------------------- mosaic and DNG


def test_dng_round_trip_through_rawpy(tmp_path):
    import rawpy

    from lensfit.io.stack import load_stack
    from synth.stack import write_stack

    board = {"target": "checkerboard", "squares": [6, 4], "square_mm": 40.0, "distance_mm": 1500.0}
    for pattern, expected_pattern in [("RGGB", [[0, 1], [3, 2]]), ("GBRG", [[3, 2], [0, 1]])]:
        sc = scene([board], effects=("defocus", "exposure", "mosaic", "noise"), N=5.6, w=96, h=64, method="convolve",
                   background=0.3, exposure={"shutter_s": 0.02, "iso": 200}, sensor={"preset": "full-frame-24mp"},
                   mosaic={"pattern": pattern})
        res = render(sc)
        out = write_stack(res, tmp_path / pattern)
        name = next(iter(res.raw))
        assert name.endswith(".dng")
        with rawpy.imread(str(out / name)) as raw:
            assert np.array_equal(raw.raw_image_visible, res.raw[name])
            # LibRaw numbers the second green 3
            assert raw.raw_pattern.tolist() == expected_pattern
            assert raw.black_level_per_channel == [512] * 4
            assert raw.white_level == 2**14 - 1
            assert raw.other.aperture == pytest.approx(5.6, rel=1e-6)
            assert raw.other.focal_length == pytest.approx(50.0, rel=1e-6)
            assert raw.other.shutter_speed == pytest.approx(0.02, rel=1e-6)
    # lensfit reads the DNG stack back to linear values: (DN - black) / (white - black)
    stack = load_stack(out)
    linear = stack.read(0)
    expected = (res.raw[name].astype(np.float64) - 512) / (2**14 - 1 - 512)
    inner = (slice(4, -4), slice(4, -4))
    assert np.median(np.abs(linear[inner] - expected[inner])) < 0.01


def test_mosaic_without_colour_effects_renders_one_channel(monkeypatch):
    import synth.convolve as C

    calls = []
    real = C.render_convolve
    monkeypatch.setattr(C, "render_convolve", lambda *a, **k: calls.append(1) or real(*a, **k))
    board = {"target": "checkerboard", "squares": [6, 4], "square_mm": 40.0, "distance_mm": 1500.0}
    res = render(scene([board], effects=("defocus", "mosaic"), w=64, h=48, method="convolve"))
    assert len(calls) == 1 and next(iter(res.images.values())).ndim == 2
    # grey targets: every photosite holds the one channel, quantised to 16 bits
    img = next(iter(res.images.values()))
    assert np.array_equal(next(iter(res.raw.values())), np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))


# --------------------------------------------------------------------------- only what is called for

STAGES = [("synth.effects.diffraction", "apply"), ("synth.effects.vignetting", "apply_natural"),
          ("synth.effects.distortion", "warp"), ("synth.effects.exposure", "mean_electrons"),
          ("synth.effects.exposure", "readout"), ("synth.effects.noise", "draw"),
          ("synth.effects.noise", "generator"), ("synth.effects.mosaic", "apply"),
          ("synth.effects.mosaic", "write_dng"), ("synth.effects.aperture", "kernel"),
          ("synth.geometry.ChannelCamera", "for_channel")]


def _forbid(monkeypatch, allowed=()):
    import importlib

    for module, fn in STAGES:
        if fn in allowed:
            continue
        try:
            target = importlib.import_module(module)
        except ModuleNotFoundError:
            mod, cls = module.rsplit(".", 1)
            target = getattr(importlib.import_module(mod), cls)

        def boom(*a, _n=f"{module}.{fn}", **k):
            raise AssertionError(f"{_n} ran although the scene does not call for it")

        monkeypatch.setattr(target, fn, boom)


BOARD = {"target": "charuco", "squares": [5, 4], "square_mm": 12.0, "marker_mm": 9.0, "dictionary": "DICT_4X4_50",
         "distance_mm": 1500.0, "tilt_deg": [20.0, 0.0]}


@pytest.mark.parametrize("method", ["raytrace", "convolve"])
def test_no_effect_stage_runs_and_the_image_is_bit_identical_to_the_bare_renderer(monkeypatch, method, tmp_path):
    from synth.convolve import render_convolve
    from synth.raytrace import render_raytrace
    from synth.stack import write_stack

    board = dict(BOARD) if method == "raytrace" else {**BOARD, "tilt_deg": [0.0, 0.0]}
    sc = scene([board], w=80, h=64, method=method, spp=16, seed=5)
    _forbid(monkeypatch)
    res = render(sc)
    write_stack(res, tmp_path / "s")  # writing calls no effect either
    img = the_image(res)
    shot = sc.shots[0]
    # the pipeline before effects existed: the render method alone
    bare = (render_raytrace(shot, 0.0, 16, res.truth["images"][0]["seed"]) if method == "raytrace"
            else render_convolve(shot, 0.0, 4))
    assert np.array_equal(img, bare)
    assert not res.raw and res.truth["effects"] == ["defocus"]


def test_only_the_listed_stage_runs(monkeypatch):
    big = {"target": "uniform", "value": 0.8, "distance_mm": 1000.0, "size_mm": [5000.0, 5000.0]}
    sc = scene([big], effects=("defocus", "vignetting"), w=32, h=32, method="convolve")
    _forbid(monkeypatch, allowed=("apply_natural",))
    render(sc)
    monkeypatch.undo()
    sc = scene([big], effects=("defocus", "exposure"), w=32, h=32, method="convolve", exposure={"shutter_s": 0.01},
               sensor={"preset": "smartphone-12mp"})
    _forbid(monkeypatch, allowed=("mean_electrons", "readout"))
    render(sc)


def test_with_noise_off_two_seeds_give_the_same_image():
    big = {"target": "checkerboard", "squares": [4, 4], "square_mm": 50.0, "distance_mm": 1200.0}
    common = dict(effects=("defocus", "diffraction", "vignetting", "distortion", "exposure"), w=64, h=48,
                  method="convolve", exposure={"shutter_s": 0.02}, sensor={"preset": "full-frame-24mp"},
                  distortion={"k1": -0.1})
    a = render(scene([big], seed=1, **common))
    b = render(scene([big], seed=2, **common))
    assert np.array_equal(next(iter(a.raw.values())), next(iter(b.raw.values())))
    noisy = dict(common, effects=common["effects"] + ("noise",))
    c = render(scene([big], seed=1, **noisy))
    d = render(scene([big], seed=2, **noisy))
    assert not np.array_equal(next(iter(c.raw.values())), next(iter(d.raw.values())))


def test_plan_lists_only_the_stages_called_for():
    from synth.rendering import plan

    big = {"target": "uniform", "value": 0.8, "distance_mm": 1000.0, "size_mm": [5000.0, 5000.0]}
    p = plan(scene([big], w=32, h=32, method="convolve"))[0]
    assert [s.split(" ")[0] for s in p.stages] == ["defocus", "quantise"]
    p = plan(scene([big], effects=("defocus", "noise", "exposure", "diffraction"), w=32, h=32,
                   exposure={"shutter_s": 0.01}, sensor={"preset": "smartphone-12mp"}))[0]
    assert [s.split(" ")[0] for s in p.stages] == ["defocus", "diffraction", "exposure", "noise", "readout"]
    assert len(p.stage_seconds) == len(p.stages) and p.estimated_s == pytest.approx(sum(p.stage_seconds))
    # the render times the same stages (and no others)
    res = render(scene([big], effects=("defocus", "noise", "exposure", "diffraction"), w=32, h=32,
                       exposure={"shutter_s": 0.01}, sensor={"preset": "smartphone-12mp"}))
    assert list(next(iter(res.stage_seconds.values()))) == ["defocus", "diffraction", "exposure", "noise", "readout"]


def test_truth_records_every_effect_and_its_parameters():
    big = {"target": "checkerboard", "squares": [4, 4], "square_mm": 50.0, "distance_mm": 1200.0}
    sc = scene([big], effects=("defocus", "aperture", "diffraction", "vignetting", "distortion",
                               "chromatic_aberration", "exposure", "mosaic", "noise"), w=48, h=32, method="convolve",
               aperture={"shape": "polygon", "blades": 7, "rotation_deg": 3.0},
               distortion={"k1": -0.05, "p2": 0.001}, chromatic_aberration={"focal_shift_mm": [0.02, 0, -0.02]},
               exposure={"shutter_s": 0.01, "iso": 800}, sensor={"preset": "aps-c-24mp", "read_noise_e": 4.0},
               mosaic={"pattern": "BGGR"})
    t = render(sc).truth
    p = t["effect_parameters"]
    assert p["aperture"]["blades"] == 7 and p["aperture"]["rotation_deg"] == 3.0
    assert p["distortion"]["k1"] == -0.05 and p["distortion"]["p2"] == 0.001
    assert p["chromatic_aberration"]["focal_shift_mm"] == [0.02, 0.0, -0.02]
    assert p["sensor"]["read_noise_e"] == 4.0 and p["sensor"]["full_well_e"] == 35000.0
    assert p["mosaic"]["pattern"] == "BGGR" and p["diffraction"]["wavelength_nm"] == [610.0, 550.0, 465.0]
    assert p["vignetting"]["natural"] and p["noise"]["shot"] and p["channels"] == ["red", "green", "blue"]
    image = t["images"][0]
    assert image["exposure"]["iso"] == 800 and image["exposure"]["shutter_s"] == 0.01
    assert image["diffraction"]["first_dark_ring_radius_px"][1] > 0
    assert t["effects"][-1] == "noise"


@pytest.mark.parametrize("change, field", [
    ({"diffraction": {"wavelength_nm": 500}}, "diffraction"),
    ({"render": {"effects": ["defocus", "noise"]}}, "render.effects"),
    ({"lens": {"aperture": {"shape": "polygon", "blades": 6}}}, "lens.aperture"),
    ({"render": {"effects": ["defocus", "exposure"]}}, "exposure.shutter_s"),
    ({"render": {"effects": ["defocus", "exposure"]}, "exposure": {"shutter_s": 0.01}}, "sensor"),
    ({"render": {"effects": ["defocus", "exposure"]}, "exposure": {"shutter_s": 0.01},
      "sensor": {"preset": "no-such"}}, "sensor.preset"),
    ({"render": {"effects": ["defocus", "mosaic"], "format": "png"}}, "render.format"),
    ({"render": {"effects": ["defocus", "distortion"]}}, "distortion"),
    ({"render": {"effects": ["diffraction"]}}, "render.effects"),
    ({"render": {"effects": ["defocus", "chromatic_aberration"]},
      "chromatic_aberration": {"focal_shift_mm": [0.1, 0.05, 0.0]}}, "chromatic_aberration.focal_shift_mm[1]"),
])
def test_inconsistent_effect_specs_are_refused_naming_the_field(change, field):
    data = {"camera": {"pixel_pitch_mm": 0.006, "width_px": 32, "height_px": 32},
            "lens": {"focal_length_mm": 50.0, "f_number": 4.0, "focus_distance_mm": 2000.0},
            "object": [{"target": "uniform", "distance_mm": 1500.0, "size_mm": [100.0, 100.0]}]}
    for key, value in change.items():
        data[key] = {**data.get(key, {}), **value}
    with pytest.raises(SpecError) as err:
        scene_from_dict(data, "scene.toml")
    assert f"{field}:" in str(err.value) or f"{field} " in str(err.value)


def test_preview_shows_what_the_files_record():
    """Sensor DN linearised with the levels is the radiance times the exposure's scale; a Bayer
    frame of a grey scene shows equal colour channels."""
    from synth.preview import recorded

    board = {"target": "checkerboard", "squares": [4, 4], "square_mm": 50.0, "distance_mm": 1200.0}
    for effects in (("defocus", "exposure"), ("defocus", "exposure", "mosaic")):
        res = render(scene([board], effects=effects, w=64, h=48, method="convolve", background=0.3,
                           exposure={"shutter_s": 0.01, "iso": 200}, sensor={"preset": "full-frame-24mp"}))
        name = next(iter(res.images))
        e = res.truth["images"][0]["exposure"]
        scale = e["electrons_per_unit"] * e["gain_dn_per_e"] / (e["white_level_dn"] - e["black_level_dn"])
        shown = recorded(res)[name]
        expected = res.images[name].astype(np.float64) * scale
        if shown.ndim == 3:  # 2 x 2 super-pixels: compare cell means, every channel
            cells = expected[:48, :64].reshape(24, 2, 32, 2).mean(axis=(1, 3))
            for c in range(3):
                got = shown[::2, ::2, c]
                assert np.abs(got - cells).max() < 0.05  # edges inside a cell differ by the cell's spread
                assert np.median(np.abs(got - cells)) < 1e-3
        else:
            assert np.abs(shown - expected).max() < 1.0 / (e["white_level_dn"] - e["black_level_dn"])
