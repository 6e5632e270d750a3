"""lensfit.optics against independent forms, limits, published values and properties."""

from __future__ import annotations

import doctest
import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lensfit import optics
from lensfit.errors import InputError

RNG = np.random.default_rng(20261122)


def log_uniform(lo, hi, n):
    return np.exp(RNG.uniform(np.log(lo), np.log(hi), n))


def test_docstring_examples():
    import importlib

    attempted = 0
    for part in ("thin", "dof", "formats", "exposure"):  # the optics package's modules
        result = doctest.testmod(importlib.import_module(f"lensfit.optics.{part}"))
        assert result.failed == 0, part
        attempted += result.attempted
    assert attempted > 20


def test_float64_without_global_side_effect():
    before = jax.config.jax_enable_x64
    out = optics.coc_diameter(50.0, 2.8, 2000.0, 1000.0)
    assert out.dtype == np.float64
    assert jax.config.jax_enable_x64 == before


def test_vectorised_broadcasting():
    d = np.array([500.0, 1000.0, 3000.0, 5000.0])
    c = optics.coc_diameter(50.0, np.array([[2.0], [4.0], [8.0]]), 2000.0, d)
    assert c.shape == (3, 4)
    # Halving the aperture halves the blur.
    np.testing.assert_allclose(c[0] / c[1], 2.0, rtol=1e-12)


# --------------------------------------------------------------------------- thin lens


def test_object_image_object_round_trip_real_and_virtual():
    f = log_uniform(1.0, 2000.0, 4000)
    d = f * log_uniform(1e-3, 1e5, 4000)
    d = d[np.abs(d / f - 1) > 1e-6]
    f = f[: d.size]
    z = optics.image_distance(f, d)
    back = optics.object_distance(f, z)
    np.testing.assert_allclose(back, d, rtol=1e-8)
    # Real image beyond f for objects beyond f; virtual (negative) inside f.
    assert np.all((np.asarray(z) > f) == (d > f))
    assert np.all((np.asarray(z) < 0) == (d < f))


def test_virtual_image_magnifier():
    # Object at f/2: the classic magnifier, virtual upright image at -f, twice the size.
    z = float(optics.image_distance(100.0, 50.0))
    assert z == pytest.approx(-100.0, rel=1e-12)
    assert float(optics.magnification(100.0, 50.0)) == pytest.approx(-2.0, rel=1e-12)


def test_limits_at_infinity_and_unit_magnification():
    assert float(optics.image_distance(35.0, math.inf)) == 35.0
    assert float(optics.object_distance(35.0, math.inf)) == 35.0
    assert float(optics.sensor_distance(35.0, math.inf)) == 35.0
    assert float(optics.magnification(35.0, math.inf)) == 0.0
    # 1:1 macro: object and image both at 2f, magnification 1, 4f sensor-to-subject.
    assert float(optics.image_distance(60.0, 120.0)) == pytest.approx(120.0, rel=1e-12)
    assert float(optics.magnification(60.0, 120.0)) == pytest.approx(1.0, rel=1e-12)
    assert float(optics.focus_distance_from_sensor(60.0, 120.0)) == pytest.approx(240.0, rel=1e-12)


def test_focus_distance_from_sensor_minimum_is_4f():
    f = 50.0
    D = f * np.linspace(1.01, 20.0, 2000)
    total = np.asarray(optics.focus_distance_from_sensor(f, D))
    assert total.min() >= 4 * f * (1 - 1e-12)
    assert total[np.argmin(total)] == pytest.approx(4 * f, rel=1e-3)


def test_aperture_f_number_inverse():
    f = log_uniform(1.0, 1000.0, 500)
    N = log_uniform(0.5, 128.0, 500)
    np.testing.assert_allclose(optics.f_number(f, optics.aperture_diameter(f, N)), N, rtol=1e-13)


# --------------------------------------------------------------------------- circle of confusion


def test_coc_two_forms_agree_over_wide_ranges():
    n = 20000
    f = log_uniform(1.0, 2000.0, n)
    N = log_uniform(0.5, 128.0, n)
    D = f * (1.0 + log_uniform(1e-4, 1e5, n))
    d = f * log_uniform(1e-2, 1e6, n)  # includes objects inside f (virtual images)
    d = np.where(np.abs(d / f - 1) < 1e-6, 2 * f, d)
    A = optics.aperture_diameter(f, N)
    s = optics.sensor_distance(f, D)
    z = optics.image_distance(f, d)
    image_side = np.asarray(optics.coc_diameter_image_side(A, s, z))
    object_side = np.asarray(optics.coc_diameter_object_side(A, s, D, d))
    direct = np.asarray(optics.coc_diameter(f, N, D, d))
    scale = np.asarray(A)  # both forms are A * (a dimensionless factor)
    np.testing.assert_allclose(image_side / scale, object_side / scale, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(direct, object_side, rtol=1e-12, atol=0)


def test_coc_zero_at_focus_and_limit_at_infinity():
    f, N, D = 85.0, 1.4, 3000.0
    assert float(optics.coc_diameter(f, N, D, D)) == 0.0
    s = float(optics.sensor_distance(f, D))
    assert float(optics.coc_diameter(f, N, D, math.inf)) == pytest.approx((f / N) * s / D, rel=1e-12)
    # Focused at infinity: a point at d has C = A f / d.
    assert float(optics.coc_diameter(f, N, math.inf, 5000.0)) == pytest.approx((f / N) * f / 5000.0, rel=1e-12)


def test_coc_is_linear_in_inverse_depth_on_each_side():
    f, N, D = 50.0, 2.8, 2000.0
    inv = np.linspace(1 / 10000, 1 / 600, 50)
    c = np.asarray(optics.coc_diameter(f, N, D, 1 / inv))
    near = inv > 1 / D
    for side in (near, ~near):
        slope = np.polyfit(inv[side], c[side], 1)
        resid = c[side] - np.polyval(slope, inv[side])
        assert np.max(np.abs(resid)) < 1e-12
        assert abs(abs(slope[0]) - (f / N) * float(optics.sensor_distance(f, D))) < 1e-6


# --------------------------------------------------------------------------- depth of field


def _dof_grid(n=5000):
    f = log_uniform(4.0, 800.0, n)
    N = log_uniform(0.7, 64.0, n)
    C = log_uniform(0.002, 0.1, n)
    H = f * f / (N * C) + f
    D = f + (H - f) * RNG.uniform(0.01, 0.99, n)  # below hyperfocal: finite far limit
    return f, N, C, D


def test_dof_limits_are_where_coc_equals_acceptable():
    f, N, C, D = _dof_grid()
    near = optics.near_limit(f, N, C, D)
    far = optics.far_limit(f, N, C, D)
    assert np.all(np.isfinite(far))
    np.testing.assert_allclose(optics.coc_diameter(f, N, D, near), C, rtol=1e-8)
    np.testing.assert_allclose(optics.coc_diameter(f, N, D, far), C, rtol=1e-6)
    assert np.all(np.asarray(near) < D) and np.all(np.asarray(far) > D)


def test_dof_matches_hyperfocal_form_published_on_wikipedia():
    # Wikipedia, "Depth of field", "Hyperfocal distance" section and the DOFMaster formulas:
    # D_N = s (H - f) / (H + s - 2f), D_F = s (H - f) / (H - s), with H = f^2/(N c) + f.
    f, N, C, D = _dof_grid()
    H = f * f / (N * C) + f
    np.testing.assert_allclose(optics.hyperfocal_distance(f, N, C), H, rtol=1e-13)
    np.testing.assert_allclose(optics.near_limit(f, N, C, D), D * (H - f) / (H + D - 2 * f), rtol=1e-9)
    np.testing.assert_allclose(optics.far_limit(f, N, C, D), D * (H - f) / (H - D), rtol=1e-6)


def test_dof_worked_example_50mm_f8_3m():
    # The check: 50 mm, f/8, focused at 3 m, C = 0.03 mm, by hand from the course's
    # formulas: N C (D_s - f) = 0.24 * 2950 = 708, f^2 = 2500.
    near = 3000 * 2500 / (2500 + 708)
    far = 3000 * 2500 / (2500 - 708)
    assert float(optics.near_limit(50, 8, 0.03, 3000)) == pytest.approx(near, rel=1e-12)
    assert float(optics.far_limit(50, 8, 0.03, 3000)) == pytest.approx(far, rel=1e-12)
    assert float(optics.depth_of_field(50, 8, 0.03, 3000)) == pytest.approx(far - near, rel=1e-12)
    assert float(optics.hyperfocal_distance(50, 8, 0.03)) == pytest.approx(2500 / 0.24 + 50, rel=1e-12)


def test_exact_dof_equals_course_closed_form_and_approximation_ratio():
    f, N, C, D = _dof_grid()
    X = N * C * (D - f)
    closed = 2 * N * C * D * f * f * (D - f) / (f**4 - X**2)
    np.testing.assert_allclose(optics.depth_of_field(f, N, C, D), closed, rtol=1e-6)
    ratio = np.asarray(optics.depth_of_field(f, N, C, D)) / np.asarray(optics.depth_of_field_approx(f, N, C, D))
    np.testing.assert_allclose(ratio, (1 - f / D) / (1 - (X / (f * f)) ** 2), rtol=1e-6)


def test_approximation_converges_to_exact():
    # Along N C D_s / f^2 -> 0 with f/D_s -> 0 (not macro) the relative error vanishes; the
    # residual error at small N C D_s / f^2 is f/D_s (see test above).
    f, C = 50.0, 0.03
    errors = []
    for D, N in [(1000.0, 4.0), (4000.0, 0.5), (16000.0, 0.05), (64000.0, 0.005), (256000.0, 0.0005)]:
        exact = float(optics.depth_of_field(f, N, C, D))
        approx = float(optics.depth_of_field_approx(f, N, C, D))
        errors.append(abs(approx / exact - 1))
    assert errors == sorted(errors, reverse=True)
    assert errors[-1] < 3e-4


def test_far_limit_becomes_infinite_exactly_at_hyperfocal():
    for f, N, C in [(50.0, 8.0, 0.03), (24.0, 2.8, 0.019), (400.0, 5.6, 0.03), (4.25, 1.8, 0.005)]:
        H = float(optics.hyperfocal_distance(f, N, C))
        assert math.isinf(float(optics.far_limit(f, N, C, H)))
        assert math.isinf(float(optics.far_limit(f, N, C, 2 * H)))
        assert math.isinf(float(optics.far_limit(f, N, C, math.inf)))
        assert math.isinf(float(optics.depth_of_field(f, N, C, H)))
        below = float(optics.far_limit(f, N, C, H * (1 - 1e-9)))
        assert math.isfinite(below) and below > 1e6 * H
        # Focused at H, everything from H/2 is sharp.
        assert float(optics.near_limit(f, N, C, H)) == pytest.approx(H / 2, rel=1e-12)
        # Focused at infinity, the near limit is H - f (where the CoC of A f / d equals C).
        assert float(optics.near_limit(f, N, C, math.inf)) == pytest.approx(H - f, rel=1e-12)


# --------------------------------------------------------------------------- sensors, exposure


@pytest.mark.parametrize(
    "width, height, published",
    [
        # Wikipedia, "Crop factor" (table of common formats).
        (22.3, 14.9, 1.6),  # Canon APS-C
        (23.6, 15.7, 1.53),  # Nikon DX
        (17.3, 13.0, 2.0),  # Four Thirds
        (13.2, 8.8, 2.72),  # 1-inch type (Wikipedia, "Image sensor format")
        (36.0, 24.0, 1.0),
    ],
)
def test_crop_factor_published(width, height, published):
    assert float(optics.crop_factor(width, height)) == pytest.approx(published, rel=0.01)


def test_angle_of_view_published():
    # Wikipedia, "Angle of view" (table for 36 x 24 mm): 50 mm -> 39.6 deg horizontal,
    # 27.0 deg vertical, 46.8 deg diagonal; 24 mm -> 73.7 deg horizontal, 84.1 deg diagonal.
    diag = optics.FULL_FRAME_DIAGONAL_MM
    assert float(optics.field_of_view_deg(36.0, 50.0)) == pytest.approx(39.6, abs=0.05)
    assert float(optics.field_of_view_deg(24.0, 50.0)) == pytest.approx(27.0, abs=0.05)
    assert float(optics.field_of_view_deg(diag, 50.0)) == pytest.approx(46.8, abs=0.05)
    assert float(optics.field_of_view_deg(36.0, 24.0)) == pytest.approx(73.7, abs=0.05)
    assert float(optics.field_of_view_deg(diag, 24.0)) == pytest.approx(84.1, abs=0.05)
    # Focusing closer narrows the view (the sensor moves back).
    assert float(optics.field_of_view_deg(36.0, 50.0, 500.0)) < float(optics.field_of_view_deg(36.0, 50.0))


def test_equivalent_focal_length_gives_same_diagonal_view():
    # The course's example: a 4.25 mm phone lens "is a 26 mm equivalent": on a sensor whose
    # crop factor is 26/4.25 it has the diagonal view of 26 mm on full frame.
    diag_phone = optics.FULL_FRAME_DIAGONAL_MM * 4.25 / 26.0
    crop = optics.FULL_FRAME_DIAGONAL_MM / diag_phone
    assert float(optics.equivalent_focal_length_35mm(4.25, crop)) == pytest.approx(26.0, rel=1e-12)
    assert float(optics.field_of_view_deg(diag_phone, 4.25)) == pytest.approx(
        float(optics.field_of_view_deg(optics.FULL_FRAME_DIAGONAL_MM, 26.0)), rel=1e-12)
    # A 50 mm lens on a 1.5x body frames like 75 mm (widely published DX example).
    assert float(optics.equivalent_focal_length_35mm(50.0, 1.5)) == 75.0


def test_exposure_value_published():
    # Wikipedia, "Exposure value": EV 0 = f/1, 1 s; EV 15 ~ f/16, 1/125 s (ISO 100).
    assert float(optics.exposure_value(1.0, 1.0)) == 0.0
    assert float(optics.exposure_value(16.0, 1 / 125)) == pytest.approx(15.0, abs=0.05)
    assert float(optics.exposure_value(2.0, 1.0)) == pytest.approx(2.0, abs=1e-12)
    # Sunny 16 (f/16, t = 1/ISO) is the same EV_100 at every ISO: the rule is ISO-independent.
    evs = [float(optics.exposure_value(16.0, 1 / iso, iso)) for iso in (100, 200, 400, 800, 3200)]
    np.testing.assert_allclose(evs, evs[0], atol=1e-12)


def test_equivalent_exposures_keep_ev():
    n = 1000
    N, t, S = log_uniform(0.7, 64, n), log_uniform(1e-5, 30, n), log_uniform(50, 102400, n)
    N2, t2, S2 = log_uniform(0.7, 64, n), log_uniform(1e-5, 30, n), log_uniform(50, 102400, n)
    ev = optics.exposure_value(N, t, S)
    np.testing.assert_allclose(optics.exposure_value(N2, optics.equivalent_shutter_s(N, t, S, N2, S2), S2), ev,
                               atol=1e-9)
    np.testing.assert_allclose(optics.exposure_value(optics.equivalent_f_number(N, t, S, t2, S2), t2, S2), ev,
                               atol=1e-9)
    np.testing.assert_allclose(optics.exposure_value(N2, t2, optics.equivalent_iso(N, t, S, N2, t2)), ev, atol=1e-9)
    # One stop: opening from f/8 to f/5.657 (sqrt 2) halves the time.
    assert float(optics.equivalent_shutter_s(8.0, 1 / 125, 100, 8 / math.sqrt(2), 100)) == pytest.approx(1 / 250)


# --------------------------------------------------------------------------- properties


lengths = st.floats(min_value=0.5, max_value=5000.0, allow_nan=False, allow_infinity=False)
f_numbers = st.floats(min_value=0.5, max_value=128.0)
cocs = st.floats(min_value=1e-4, max_value=1.0)
factors = st.floats(min_value=1e-6, max_value=1e6)


@settings(max_examples=300, deadline=None)
@given(f=lengths, N=f_numbers, C=cocs, focus_factor=factors, obj_factor=factors)
def test_no_nan_or_unexpected_inf(f, N, C, focus_factor, obj_factor):
    D = f * (1.0 + focus_factor)
    d = f * obj_factor
    values = {
        "sensor_distance": optics.sensor_distance(f, D),
        "coc": optics.coc_diameter(f, N, D, d),
        "near": optics.near_limit(f, N, C, D),
        "hyperfocal": optics.hyperfocal_distance(f, N, C),
        "fov": optics.field_of_view_deg(36.0, f, D),
        "approx": optics.depth_of_field_approx(f, N, C, D),
    }
    if abs(obj_factor - 1.0) > 1e-9:
        values["image"] = optics.image_distance(f, d)
        values["magnification"] = optics.magnification(f, d)
    for name, v in values.items():
        assert np.all(np.isfinite(np.asarray(v))), name
    far = float(optics.far_limit(f, N, C, D))
    assert not math.isnan(far)
    H = float(optics.hyperfocal_distance(f, N, C))
    assert math.isinf(far) == (D >= H)
    assert float(values["near"]) <= D


INVALID = [float("nan"), 0.0, -1.0, float("-inf")]


@settings(max_examples=60, deadline=None)
@given(which=st.sampled_from(["focal_length_mm", "f_number", "acceptable_coc_diameter_mm", "focus_distance_mm"]),
       bad=st.sampled_from(INVALID))
def test_invalid_inputs_raise_naming_the_argument(which, bad):
    kwargs = dict(focal_length_mm=50.0, f_number=2.8, acceptable_coc_diameter_mm=0.03, focus_distance_mm=2000.0)
    kwargs[which] = bad
    for fn in (optics.near_limit, optics.far_limit, optics.depth_of_field):
        with pytest.raises(InputError) as info:
            fn(**kwargs)
        assert info.value.argument == which
        assert which in str(info.value)


def test_invalid_relations_raise():
    with pytest.raises(ValueError, match="focus_distance_mm"):
        optics.sensor_distance(50.0, 40.0)
    with pytest.raises(ValueError, match="object_distance_mm"):
        optics.image_distance(50.0, 50.0)
    with pytest.raises(ValueError, match="object_distance_mm"):
        optics.coc_diameter(50.0, 2.0, 2000.0, np.array([100.0, -5.0]))
    with pytest.raises(ValueError, match="image_distance_mm"):
        optics.coc_diameter_image_side(10.0, 50.0, 0.0)
    with pytest.raises(ValueError, match="focal_length_mm"):
        optics.aperture_diameter(math.inf, 2.0)
    with pytest.raises(ValueError, match="f_number"):
        optics.aperture_diameter(50.0, "fast")


def test_traced_call_keeps_callers_dtype():
    # Inside a caller's jit the float64 scope is the caller's; the function still traces.
    with jax.enable_x64(True):
        out = jax.jit(lambda d: optics.coc_diameter(50.0, 2.0, 2000.0, d))(np.array([1000.0, 4000.0]))
    np.testing.assert_allclose(out, optics.coc_diameter(50.0, 2.0, 2000.0, np.array([1000.0, 4000.0])), rtol=1e-12)
