"""Blur under lens distortion: the spot of a defocused point is the circle of confusion in the plane
in focus, imaged through the distortion, so an edge reads it scaled by the distortion's stretch
across the edge (lensfit.measurement.edge_geometry.distortion_scale), and measure divides that out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lensfit.calibration.camera import Intrinsics
from lensfit.measurement.edge_geometry import distortion_scale


def brown_jacobian(u, v, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0):
    """d(x_d, y_d) / d(x, y) of the Brown-Conrady model, written out by hand (not OpenCV's)."""
    r2 = u * u + v * v
    rho = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drho = k1 + 2 * k2 * r2 + 3 * k3 * r2**2  # d rho / d r^2
    dxdu = rho + 2 * u * u * drho + 2 * p1 * v + 6 * p2 * u
    dxdv = 2 * u * v * drho + 2 * p1 * u + 2 * p2 * v
    dydu = 2 * u * v * drho + 2 * p1 * u + 2 * p2 * v
    dydv = rho + 2 * v * v * drho + 6 * p1 * v + 2 * p2 * u
    return np.array([[dxdu, dxdv], [dydu, dydv]])


def intrinsics(dist):
    return Intrinsics(1000.0, (640.0, 480.0), tuple(dist), 0.0, 0, "manifest")


@pytest.mark.parametrize("r", [0.1, 0.35, 0.6])
def test_radial_distortion_scales_a_blur_radially_and_tangentially_as_the_model_says(r):
    # On the x axis: an edge along y (normal radial) reads the radial stretch d r_d / d r,
    # an edge along x the tangential one r_d / r.
    k1, k2 = -0.25, 0.05
    z = 1000.0
    point = np.array([r * z, 0.0, z])
    radial = distortion_scale(intrinsics([k1, k2, 0, 0, 0]), point, np.array([0.0, 1.0, 0.0]))
    tangential = distortion_scale(intrinsics([k1, k2, 0, 0, 0]), point, np.array([1.0, 0.0, 0.0]))
    assert radial == pytest.approx(1 + 3 * k1 * r**2 + 5 * k2 * r**4, rel=1e-8)
    assert tangential == pytest.approx(1 + k1 * r**2 + k2 * r**4, rel=1e-8)


@pytest.mark.parametrize("dist", [(-0.25, 0.05, 0.003, -0.002, 0.01), (0.15, 0.0, 0.004, -0.003, 0.0)])
@pytest.mark.parametrize("along", [(1.0, 0.0, 0.0), (0.3, 1.0, 0.0), (1.0, -0.5, 0.4)])
def test_distortion_scale_is_the_stretch_across_the_edge(dist, along):
    """Against the hand-written Jacobian: |J^T n| with n the normal of the edge's image J t."""
    z = 800.0
    point = np.array([0.31 * z, -0.22 * z, z])
    along = np.array(along)
    u, v = point[0] / z, point[1] / z
    t = np.array([along[0] * z - point[0] * along[2], along[1] * z - point[1] * along[2]])
    J = brown_jacobian(u, v, *dist)
    image_dir = J @ t
    n = np.array([-image_dir[1], image_dir[0]]) / np.linalg.norm(image_dir)
    assert distortion_scale(intrinsics(dist), point, along) == pytest.approx(np.linalg.norm(J.T @ n), rel=1e-7)


def test_no_distortion_scales_nothing():
    assert distortion_scale(intrinsics([0.0] * 5), np.array([300.0, 200.0, 900.0]), np.array([1.0, 0, 0])) == 1.0


def test_a_distorted_render_reads_the_mapped_disk():
    """A fronto-parallel checkerboard rendered by the ray tracer through barrel distortion
    (each sample traces its own undistorted ray), out of focus by a known circle of confusion:
    its edges read c times the distortion scale, up to 7 % below c near the corners (measured: the
    squeezed ones' median 5.7 % off), and the scale takes the readings back to c (their mean within
    0.01 %, every edge within 4.5 %: 64 spp)."""
    from lensfit.estimators.base import EdgeTask
    from lensfit.estimators.edge import measure
    import cv2
    from synth.rendering import render
    from synth.scene import scene_from_dict

    f, N, D, pitch, w, h, z, sq = 16.0, 2.0, 1e6, 0.05, 320, 240, 1000.0, 75.0
    k = (-0.25, 0.05, 0.0, 0.0, 0.0)
    sc = scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D},
        "render": {"samples_per_pixel": 64, "seed": 3, "method": "raytrace", "effects": ["defocus", "distortion"]},
        "background": {"value": 0.5},
        "distortion": {"k1": k[0], "k2": k[1]},
        "object": [{"target": "checkerboard", "squares": [10, 8], "square_mm": sq, "distance_mm": z}]})
    img = next(iter(render(sc).images.values())).astype(np.float64)
    s = 1.0 / (1.0 / f - 1.0 / D)
    c = (f / N) * (s / pitch) * abs(1.0 / D - 1.0 / z)  # CoC diameter, undistorted px (2.56)
    intr = Intrinsics(s / pitch, ((w - 1) / 2, (h - 1) / 2), k, 0.0, 0, "manifest")
    K = intr.camera_matrix
    tasks, scales = [], []
    for j in range(1, 8):  # the vertical edges between inner corners (i, j) and (i, j + 1), and horizontals
        for i in range(1, 10):
            for di, dj in ((0, 1), (1, 0)):
                if i + di > 9 or j + dj > 7:
                    continue
                a = np.array([(i - 5) * sq, (j - 4) * sq, z])
                b = np.array([(i + di - 5) * sq, (j + dj - 4) * sq, z])
                px = cv2.projectPoints(np.array([a, b]), np.zeros(3), np.zeros(3), K, np.array(k))[0].reshape(2, 2)
                room = 0.3 * np.linalg.norm(px[1] - px[0])
                tasks.append(EdgeTask(px[0], px[1], room, room))
                scales.append(distortion_scale(intr, (a + b) / 2, b - a))
    read = measure(img, tasks, second_moment=False)
    ok = [k for k, e in enumerate(read) if e.coc_diameter_px is not None]
    assert len(ok) > 100
    reading = np.array([read[k].coc_diameter_px for k in ok])
    g = np.array([scales[k] for k in ok])
    assert g.min() < 0.93  # the outer edges are squeezed by 5-7 %
    outer = g < 0.96
    # Read as c alone they are far off; through the scale within a few per cent, edge by edge,
    # and within 1 % on average over the squeezed ones.
    assert np.median(np.abs(reading[outer] / c - 1)) > 0.04
    assert np.max(np.abs(reading / (c * g) - 1)) < 0.06
    assert abs(np.mean(reading[outer] / (c * g[outer])) - 1) < 0.01


def test_measure_reads_a_distorted_stack_in_undistorted_pixels(tmp_path):
    """The whole measure on a ray-traced stack through barrel distortion, its intrinsics given in
    stack.toml: every edge's reading is flagged ``distortion_scaled`` and follows the circle of
    confusion of its distance (thin-lens formula, synth's truth) with no trend over the field,
    where the image's own readings fall 5-7 % below it at the outer edges."""
    from lensfit.measurement.measure import measure
    from synth.rendering import render
    from synth.scene import scene_from_dict
    from synth.stack import write_stack

    f, N, D, pitch, w, h, z = 16.0, 2.0, 1e6, 0.05, 320, 240, 1000.0
    sc = scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": w, "height_px": h},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D},
        "render": {"samples_per_pixel": 64, "seed": 5, "method": "raytrace", "effects": ["defocus", "distortion"]},
        "background": {"value": 0.5},
        "distortion": {"k1": -0.25, "k2": 0.05},
        "object": [{"id": "board", "target": "checkerboard", "squares": [10, 8], "square_mm": 75.0,
                    "distance_mm": z}]})
    stack = write_stack(render(sc), tmp_path / "stack")
    s = 1.0 / (1.0 / f - 1.0 / D)
    manifest = stack / "stack.toml"
    manifest.write_text(manifest.read_text() + f'\n[[intrinsics]]\nsetting = "a"\nfocal_length_px = {s / pitch}\n'
                        f'principal_point_px = [{(w - 1) / 2}, {(h - 1) / 2}]\ndistortion = [-0.25, 0.05, 0, 0, 0]\n')
    table = measure(stack, "edge-disk")
    read = [smp for smp in table.samples if smp.coc_diameter_px is not None]
    assert len(read) > 80
    assert all("distortion_scaled" in smp.flags for smp in read)
    ratio = np.array([smp.coc_diameter_px / ((f / N) * (s / pitch) * abs(1 / D - 1 / smp.distance_mm)) for smp in read])
    r2 = np.array([smp.field_radius_px for smp in read]) ** 2 / (s / pitch) ** 2
    slope = np.polyfit(r2, ratio, 1)[0]
    # uncorrected, the radial profiles would fall as 1 + 3 k1 r^2: a slope near -0.75
    assert abs(slope) < 0.08, slope
    assert abs(np.median(ratio) - 1) < 0.01


def test_a_real_telephotos_spot_stretches_as_its_distortion_maps_the_plane_in_focus():
    """Through a real compound lens (the shipped telephoto-250 prescription, f/11, pincushion), a
    defocused point's real-ray spot off axis, against the same point on axis: across radial and
    tangential directions it is stretched as the lens's own mapping of the plane in focus (chief
    rays) says, and as lensfit.measurement.edge_geometry.distortion_scale says from OpenCV coefficients
    fitted to that mapping. Field curvature also scales an off-axis spot, oppositely in front of
    and behind focus, so each ratio is the geometric mean over two depths about as far in front
    of focus as behind (0.7 X and 1.7 X: the curvature cancels to first order). Measured 0.06 and
    0.10 off axis (in tan), radial / tangential: the stretch 1.0067 / 1.0022 and 1.0191 / 1.0063,
    the spots 1.0065 / 1.0021 and 1.0156 / 1.0059: within a quarter of the stretch, where a spot
    that ignored the distortion would sit at 1."""
    from lensfit.calibration.camera import Intrinsics
    from synth.geometry import CompoundLensCamera
    from synth.lens import load_prescription, paraxial, trace
    from synth.lens.focus import disk_grid

    rx = load_prescription("telephoto-250")
    efl = paraxial(rx).efl_mm
    pitch, X = 0.006 * efl / 25.0, 40.0 * efl
    cam = CompoundLensCamera(focal_length_mm=efl, f_number=11.0, focus_distance_mm=X, pixel_pitch_mm=pitch,
                             width_px=1200, height_px=800, prescription=rx)
    fpx = cam.sensor_distance_mm / pitch
    reach = 0.75 * cam.paraxial.entrance_pupil_diameter_mm + 0.1 * efl

    def spot(depth, tan_field):
        """The real rays' landing points (px) of a point at ``depth`` and field ``tan_field`` (x)."""
        u, v = disk_grid(201)
        ox, oz = tan_field * depth, cam.scene_origin_z_mm - depth
        d = np.stack([reach * u - ox, reach * v, np.full_like(u, cam.scene_origin_z_mm - oz)])
        d /= np.linalg.norm(d, axis=0)
        (x, y, z), (dx, dy, dz), ok, _ = trace(cam.stopped, (np.full_like(u, ox), 0 * u, np.full_like(u, oz)),
                                               tuple(d))
        ok &= dz > 1e-9
        t = (cam.sensor_z_mm - z[ok]) / dz[ok]
        return (x[ok] + t * dx[ok]) / pitch, (y[ok] + t * dy[ok]) / pitch

    def height(tan_field):  # the mapping of the plane in focus: where the point at X lands, / f_px
        return abs(np.mean(spot(X, tan_field)[0])) / fpx

    # OpenCV's k1, k2 fitted to the mapping (r_d / r - 1 = k1 r^2 + k2 r^4), as a calibration finds
    fields = np.linspace(0.02, 0.16, 8)
    k1, k2 = np.linalg.lstsq(np.column_stack([fields**2, fields**4]), [height(r) / r - 1 for r in fields],
                             rcond=None)[0]
    intr = Intrinsics(fpx, (599.5, 399.5), (k1, k2, 0.0, 0.0, 0.0), 0.0, 0, "manifest")
    on_axis = {depth: spot(depth, 0.0) for depth in (0.7 * X, 1.7 * X)}
    for r in (0.06, 0.10):
        h = 1e-4
        stretch = {"radial": (height(r + h) - height(r - h)) / (2 * h), "tangential": height(r) / r}
        point = np.array([r * X, 0.0, X])
        model = {"radial": distortion_scale(intr, point, np.array([0.0, 1.0, 0.0])),  # edge along y: normal radial
                 "tangential": distortion_scale(intr, point, np.array([1.0, 0.0, 0.0]))}
        for axis, j in (("radial", 0), ("tangential", 1)):
            ratio = math.sqrt(np.prod([np.std(spot(depth, r)[j]) / np.std(on_axis[depth][j]) for depth in on_axis]))
            assert stretch[axis] > 1.0 + 0.5 * r**2  # pincushion, enough to tell apart from 1
            # (what field curvature leaves at second order grows as r^4: 0.0035 of 0.019 at 0.10)
            assert abs(ratio - stretch[axis]) < 0.25 * (stretch[axis] - 1.0), (r, axis, ratio, stretch[axis])
            assert model[axis] == pytest.approx(stretch[axis], abs=0.002), (r, axis)


def test_where_the_model_folds_the_image_there_is_no_scale():
    """k1 = -0.5 folds the image over itself beyond r^2 = 2/3 (d r_d / d r = 1 + 3 k1 r^2 < 0): no
    scale there (NaN, which measure turns into no reading, flag distortion_extreme), a scale inside."""
    intr = intrinsics([-0.5, 0.0, 0.0, 0.0, 0.0])
    assert math.isnan(distortion_scale(intr, np.array([1000.0, 0.0, 1000.0]), np.array([0.0, 1.0, 0.0])))
    assert distortion_scale(intr, np.array([300.0, 0.0, 1000.0]), np.array([0.0, 1.0, 0.0])) == pytest.approx(
        1 - 1.5 * 0.09, rel=1e-8)


def test_readings_are_divided_by_the_scale_or_dropped_beyond_its_range():
    from lensfit.estimators.base import BlurEstimate
    from lensfit.measurement.edge_geometry import undistorted_blur

    est = BlurEstimate(4.0, 0.2, ("shaped_spot",), disk_diameter_px=3.8, disk_sigma_px=0.1)
    flags: list[str] = []
    got = undistorted_blur(est, 0.8, flags)
    assert (got.coc_diameter_px, got.sigma_px, got.disk_diameter_px, got.disk_sigma_px) == pytest.approx(
        (5.0, 0.25, 4.75, 0.125)) and flags == ["distortion_scaled"]
    for bad in (float("nan"), 0.1, 6.0):
        flags = []
        got = undistorted_blur(est, bad, flags)
        assert got.coc_diameter_px is None and got.sigma_px is None and flags == ["distortion_extreme"]
    flags = []
    assert undistorted_blur(est, 1.0, flags) is est and flags == []


def test_lensfit_fit_says_when_the_readings_went_through_a_distortion(calibration_samples, capsys):
    """The printed results name the calibrated distortion the blur was read through, and say
    nothing of it where the calibration found none."""
    from lensfit.cli.fit import print_fit
    from lensfit.fitting import fit, results_document

    result = fit(calibration_samples)
    document = results_document(result, ["lensfit", "fit"], intrinsics=calibration_samples.intrinsics)
    label = next(iter(document["calibration"]))
    assert not any(document["calibration"][label]["distortion_opencv"])
    print_fit(result, document)
    assert "lens distortion" not in capsys.readouterr().out
    document["calibration"][label] = {**document["calibration"][label],
                                      "distortion_opencv": [-0.25, 0.05, 0.0, 0.0, 0.0]}
    print_fit(result, document)
    assert "lens distortion k1 -0.25, k2 +0.05: each edge's blur is read through it" in capsys.readouterr().out


def test_a_bowed_edges_fitted_line_is_moved_through_its_true_ends():
    """Barrel distortion images a straight target edge as a curve, which the edge estimator fits
    with a straight line that misses the edge's ends (the corners refined from it) by most of the
    bow's depth; lensfit.measurement.edge_geometry.unbowed moves it through them. The image is drawn here
    with no renderer: every pixel's sub-samples undistorted by OpenCV, a disk-blurred step at
    their distance from the straight edge in the undistorted image."""
    import cv2
    from types import SimpleNamespace

    from lensfit.measurement.edge_geometry import bow_margin, unbowed
    from lensfit.estimators import EdgeTask, get_estimator

    f_px, centre, dist = 3000.0, (600.0, 400.0), (-0.25, 0.0, 0.0, 0.0, 0.0)
    intr = Intrinsics(f_px, centre, dist, 0.0, 1, "manifest")
    z_mm, y_mm, c_px = 1000.0, 110.0, 4.0  # the edge y = 110 mm, x 150-200 mm, 1 m away: r 0.19-0.23
    pose = SimpleNamespace(to_camera=lambda p: np.column_stack([np.atleast_2d(p)[:, :2], np.full(len(np.atleast_2d(p)), z_mm)]))
    seg = SimpleNamespace(start_mm=(150.0, y_mm), end_mm=(200.0, y_mm))
    ends = cv2.projectPoints(np.array([[150.0, y_mm, z_mm], [200.0, y_mm, z_mm]]), np.zeros(3), np.zeros(3),
                             intr.camera_matrix, np.array(dist))[0].reshape(2, 2)
    x0, y0 = (np.floor(ends.min(axis=0)) - 40).astype(int)  # drawn where the estimator looks
    x1, y1 = (np.ceil(ends.max(axis=0)) + 40).astype(int)
    image = np.zeros((y1 + 20, x1 + 20))
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    for dy in sub:
        for dx in sub:
            pts = np.column_stack([(xs + dx).ravel(), (ys + dy).ravel()]).reshape(-1, 1, 2)
            und = cv2.undistortPoints(pts, intr.camera_matrix, np.array(dist),
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
            und = und.reshape(*xs.shape, 2)
            u = np.clip((und[..., 1] - y_mm / z_mm) * f_px / (c_px / 2), -1.0, 1.0)  # across the edge, in radii
            image[y0:y1, x0:x1] += (0.5 + (u * np.sqrt(1 - u * u) + np.arcsin(u)) / np.pi) / 16
    image[:y0] = 0.0
    image[y1:] = 1.0
    image = 0.2 + 0.6 * image
    task = EdgeTask(ends[0], ends[1], 25.0, 25.0, context={})
    est = get_estimator("edge")(image, [task])[0]
    stretch = distortion_scale(intr, np.array([175.0, y_mm, z_mm]), np.array([1.0, 0.0, 0.0]))
    assert abs(est.coc_diameter_px / (c_px * stretch) - 1) < 0.01

    def misses(line):
        q0, q1 = (np.asarray(q, float) for q in line)
        n = np.array([-(q1 - q0)[1], (q1 - q0)[0]]) / np.linalg.norm(q1 - q0)
        return np.array([(ends[0] - q0) @ n, (ends[1] - q0) @ n])

    before = misses(est.line_px)
    after = misses(unbowed(est.line_px, seg, pose, intr, bow_margin(task, est)))
    assert np.all(np.abs(before) > 0.03), before  # seen: 0.035 and 0.041 px; after, 0.005 and 0.001
    assert np.all(np.abs(after) < 0.2 * np.abs(before)), (before, after)
    assert unbowed(est.line_px, seg, pose, intrinsics((0.0,) * 5), 10.0) is est.line_px


def test_a_distortion_only_the_refined_corners_show_moves_the_lines_again(calibration_stack, monkeypatch):
    """Where the calibration from OpenCV's corners (about 0.1 px) finds no distortion and the one
    from the refined corners does, measure refines the corners again, each line moved through that
    distortion with the views' poses under it, and calibrates once more; where neither finds
    one (this stack has none), twice."""
    import dataclasses

    import lensfit.measurement.measure as m
    import lensfit.measurement.views as views

    real_calibrate, real_refined = views.calibrate, m.refined_detections
    for inject in (False, True):
        calls, fresh = [], []

        def calibrate(dets, shape, **kw):
            out = real_calibrate(dets, shape, **kw)
            calls.append(out)
            if inject and len(calls) == 2:  # the refined corners' calibration finds a barrel
                out = {k: dataclasses.replace(v, distortion=(-0.1, 0.0, 0.0, 0.0, 0.0)) for k, v in out.items()}
            return out

        def refined(*args, fresh_poses=False, **kw):
            fresh.append(fresh_poses)
            return real_refined(*args, fresh_poses=fresh_poses, **kw)

        monkeypatch.setattr(views, "calibrate", calibrate)
        monkeypatch.setattr(m, "refined_detections", refined)
        table = m.measure(calibration_stack)
        assert not any(np.any(v.distortion) for v in calls[0].values())
        images = len(table.corners_px)
        assert len(calls) == (3 if inject else 2)
        assert fresh == [False] * images + ([True] * images if inject else [])
