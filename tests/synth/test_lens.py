"""synth.lens (compound-lens prescriptions, paraxial data, exact ray tracing) against optiland,
an independent optics library (a test dependency), on every shipped design: real ray heights
at every surface to 1e-9 mm, EFL, focal and principal planes and pupils to 1e-9 relative."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from lensfit.errors import SpecError
from synth.lens import list_prescriptions, load_prescription, paraxial, prescription_from_dict, reverse, trace

optiland = pytest.importorskip("optiland")
warnings.filterwarnings("ignore", category=DeprecationWarning)

DESIGNS = ["double-gauss-50", "cooke-triplet-50", "telephoto-250", "retrofocus-24"]


def to_optiland(rx, bfl):
    from optiland import optic
    from optiland.materials import IdealMaterial

    lens = optic.Optic()
    lens.surfaces.add(index=0, radius=np.inf, thickness=np.inf)
    n = len(rx.surfaces)
    for i, s in enumerate(rx.surfaces, start=1):
        kw = {"index": i, "radius": s.radius_mm, "thickness": s.thickness_mm if i < n else bfl, "is_stop": s.stop}
        if s.n != 1.0:
            kw["material"] = IdealMaterial(n=s.n)
        lens.surfaces.add(**kw)
    lens.surfaces.add(index=n + 1)
    lens.set_aperture(aperture_type="EPD", value=paraxial(rx).entrance_pupil_diameter_mm)
    lens.fields.set_type(field_type="angle")
    lens.fields.add(y=0)
    lens.wavelengths.add(value=0.58756, is_primary=True)
    return lens


def test_the_four_designs_ship():
    assert set(DESIGNS) <= set(list_prescriptions())


@pytest.mark.parametrize("name", DESIGNS)
def test_paraxial_data_match_optiland(name):
    rx = load_prescription(name)
    ours = paraxial(rx)
    lens = to_optiland(rx, ours.bfl_mm)
    pa = lens.paraxial
    z_last = float(rx.vertices_mm()[-1])
    image_z = z_last + ours.bfl_mm
    rel = 1e-9
    assert ours.efl_mm == pytest.approx(float(pa.f2()), rel=rel)
    assert ours.entrance_pupil_diameter_mm == pytest.approx(float(pa.EPD()), rel=rel)
    assert ours.entrance_pupil_z_mm == pytest.approx(float(pa.EPL()), rel=rel, abs=1e-9)
    assert ours.exit_pupil_diameter_mm == pytest.approx(float(pa.XPD()), rel=rel)
    assert ours.exit_pupil_z_mm - image_z == pytest.approx(float(pa.XPL()), rel=rel, abs=1e-9)
    assert ours.front_focal_z_mm == pytest.approx(float(pa.F1()), rel=rel, abs=1e-9)
    assert ours.rear_focal_z_mm - image_z == pytest.approx(float(pa.F2()), rel=rel, abs=1e-9)  # at the image
    assert ours.front_principal_z_mm == pytest.approx(float(pa.P1()), rel=rel, abs=1e-9)
    assert ours.rear_principal_z_mm - image_z == pytest.approx(float(pa.P2()), rel=rel, abs=1e-9)


@pytest.mark.parametrize("name", DESIGNS)
def test_real_rays_match_optiland_at_every_surface(name):
    from optiland.rays import RealRays

    rx = load_prescription(name)
    para = paraxial(rx)
    lens = to_optiland(rx, para.bfl_mm)
    rng = np.random.default_rng(3)
    m = 200
    # Rays from a point in front of the lens towards random points of the entrance pupil, some
    # off axis up to the design's field, some vignetted.
    src = np.stack([rng.uniform(-20, 20, m), rng.uniform(-20, 20, m), np.full(m, -300.0)])
    r = rng.uniform(0, 0.6, m) * para.entrance_pupil_diameter_mm
    phi = rng.uniform(0, 2 * math.pi, m)
    tgt = np.stack([r * np.cos(phi), r * np.sin(phi), np.full(m, para.entrance_pupil_z_mm)])
    d = tgt - src
    d /= np.linalg.norm(d, axis=0)
    # Both start on the plane z = -5 mm in front of the first vertex.
    t = (-5.0 - src[2]) / d[2]
    start = src + t * d
    (_, _, _), (_, _, _), passed, heights = trace(rx, tuple(start), tuple(d))
    rays = RealRays(start[0], start[1], start[2], d[0], d[1], d[2], np.ones(m), np.full(m, 0.58756))
    lens.surface_group.trace(rays)
    ox, oy = np.asarray(lens.surface_group.x), np.asarray(lens.surface_group.y)
    checked = 0
    for i, (x, y) in enumerate(heights):
        ok = passed  # optiland traces blocked rays on; compare those that pass everything
        np.testing.assert_allclose(x[ok], ox[i + 1][ok], rtol=0, atol=1e-9, err_msg=f"{name} surface {i} x")
        np.testing.assert_allclose(y[ok], oy[i + 1][ok], rtol=0, atol=1e-9, err_msg=f"{name} surface {i} y")
        checked += int(ok.sum())
    assert passed.sum() > 0.3 * m and checked > 0


@pytest.mark.parametrize("name", DESIGNS)
def test_reversed_trace_retraces_the_ray(name):
    """Light paths are reversible: trace forward, turn the exit ray around, trace the reversed
    lens, and the ray comes back to where it started (an identity optiland does not enter)."""
    rx = load_prescription(name)
    para = paraxial(rx)
    rng = np.random.default_rng(5)
    m = 100
    x0 = rng.uniform(-0.3, 0.3, m) * para.entrance_pupil_diameter_mm
    y0 = rng.uniform(-0.3, 0.3, m) * para.entrance_pupil_diameter_mm
    d = np.stack([rng.uniform(-0.05, 0.05, m), rng.uniform(-0.05, 0.05, m), np.ones(m)])
    d /= np.linalg.norm(d, axis=0)
    (x, y, z), (dx, dy, dz), passed, _ = trace(rx, (x0, y0, np.full(m, -1.0)), tuple(d))
    z_last = rx.vertices_mm()[-1]
    # In the reversed lens's frame z' = z_last - z; directions flip.
    (xb, yb, zb), (dxb, dyb, dzb), passed_b, _ = trace(reverse(rx), (x, y, z_last - z), (-dx, -dy, dz))
    ok = passed & passed_b
    t = (z_last + 1.0 - zb) / dzb  # back to the start plane z = -1
    np.testing.assert_allclose(xb[ok] + t[ok] * dxb[ok], x0[ok], atol=1e-9)
    np.testing.assert_allclose(yb[ok] + t[ok] * dyb[ok], y0[ok], atol=1e-9)
    assert ok.mean() > 0.5


def test_pupil_magnification_of_the_shipped_designs():
    """Telephotos have P < 1, retrofocus wide angles P > 1, a near-symmetric double Gauss about 1."""
    P = {name: paraxial(load_prescription(name)).pupil_magnification for name in DESIGNS}
    assert P["telephoto-250"] < 0.9 and P["retrofocus-24"] > 1.2 and 0.8 < P["double-gauss-50"] < 1.25


def test_with_f_number_sets_efl_over_entrance_pupil():
    rx = load_prescription("double-gauss-50")
    for N in (2.0, 2.8, 8.0):
        assert paraxial(rx.with_f_number(N)).f_number == pytest.approx(N, rel=1e-12)


@pytest.mark.parametrize("change,field", [
    ({"n": math.nan}, "surface[0].n"), ({"radius_mm": 0}, "surface[0].radius_mm"),
    ({"semi_aperture_mm": 40.0}, "surface[0].semi_aperture_mm"), ({"colour": 1}, "surface[0].colour"),
])
def test_bad_prescriptions_are_refused_naming_the_field(change, field):
    rows = [{"radius_mm": 29.475, "thickness_mm": 3.76, "n": 1.67, "semi_aperture_mm": 12.6},
            {"radius_mm": "inf", "thickness_mm": 3, "n": 1.0, "semi_aperture_mm": 8, "stop": True},
            {"radius_mm": -39.73, "thickness_mm": 0, "n": 1.0, "semi_aperture_mm": 10}]
    rows[0] = {**rows[0], **change}
    with pytest.raises(SpecError, match=field.replace("[", r"\[").replace("]", r"\]")):
        prescription_from_dict({"surface": rows})


@pytest.mark.parametrize("name", DESIGNS)
def test_best_focus_is_the_least_rms_plane_of_optilands_rays(name):
    """The best-focus plane (smallest RMS spot of the axial point) from rays optiland traces, by
    scanning planes; ours comes from a closed form on our own trace."""
    from optiland.rays import RealRays

    from synth.lens import best_focus_image_z, image_z

    rx = load_prescription(name).with_f_number(5.6)
    para = paraxial(rx)
    lens = to_optiland(rx, para.bfl_mm)
    X = 30 * para.efl_mm
    z_obj = para.entrance_pupil_z_mm - X
    # A polar grid of equal-area cells over the entrance pupil (overfilled: the stop clips).
    # Fine rings: the stop's edge falls between two of them, so their spacing is the sampling error.
    rho = np.sqrt((np.arange(400) + 0.5) / 400) * 0.6 * para.entrance_pupil_diameter_mm
    phi = (np.arange(90) + 0.5) / 90 * 2 * math.pi
    R, F = np.meshgrid(rho, phi)
    tgt = np.stack([(R * np.cos(F)).ravel(), (R * np.sin(F)).ravel(), np.full(R.size, para.entrance_pupil_z_mm)])
    src = np.array([0.0, 0.0, z_obj])[:, None]
    d = tgt - src
    d /= np.linalg.norm(d, axis=0)
    start = src + ((-5.0 - z_obj) / d[2]) * d
    rays = RealRays(start[0], start[1], start[2], d[0], d[1], d[2], np.ones(R.size), np.full(R.size, 0.58756))
    lens.surface_group.trace(rays)
    x, y, z = (np.asarray(getattr(lens.surface_group, k))[-1] for k in ("x", "y", "z"))
    L, M, N = (np.asarray(getattr(rays, k)) for k in ("L", "M", "N"))
    (_, _, _), (_, _, _), passed, _ = trace(rx, tuple(start), tuple(d))  # which rays the stop lets through
    x, y, z, L, M, N = (q[passed] for q in (x, y, z, L, M, N))
    z_par = image_z(rx, z_obj)
    # optiland's image-surface z is relative to its own origin: put it on ours by the last vertex.
    z = z - np.asarray(lens.surface_group.positions).ravel()[-2] + rx.vertices_mm()[-1]
    planes = z_par + np.linspace(-0.5, 0.1, 6001) * para.efl_mm / 50
    rms = [np.sqrt(np.var(x + (p - z) * L / N) + np.var(y + (p - z) * M / N)) for p in planes]
    scanned = planes[int(np.argmin(rms))]
    ours = best_focus_image_z(rx, z_obj)
    step = planes[1] - planes[0]
    assert abs(ours - scanned) < 2 * step + 0.01 * (z_par - scanned), (ours, scanned, z_par)
    assert ours < z_par  # under-corrected spherical aberration: best focus in front of the paraxial image


@pytest.mark.parametrize("name", DESIGNS)
def test_best_focus_tends_to_the_paraxial_image_as_the_stop_closes(name):
    """Third-order spherical aberration: the focus shift grows as the aperture squared, 1/N^2."""
    from synth.lens import best_focus_image_z, image_z, object_z

    base = load_prescription(name)
    shifts = []
    for N in (32.0, 64.0):
        rx = base.with_f_number(N)
        para = paraxial(rx)
        z_obj = para.entrance_pupil_z_mm - 40 * para.efl_mm
        z_par = image_z(rx, z_obj)
        assert object_z(rx, z_par) == pytest.approx(z_obj, rel=1e-9)  # the inverse of image_z
        shifts.append(z_par - best_focus_image_z(rx, z_obj))
    assert shifts[0] > 0 and shifts[0] / shifts[1] == pytest.approx(4.0, rel=0.1)
