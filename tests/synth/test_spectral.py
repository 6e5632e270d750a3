"""Spectral rendering through compound lenses: glass dispersion from a catalogue, and the
longitudinal and lateral colour it causes coming out of the trace, not added.

References: optiland's own copy of the SCHOTT catalogue and its paraxial solver (EFL per
wavelength), and a forward float64 trace of an object point through the lens at each wavelength
(``synth.lens.trace``, checked against optiland in test_lens.py) for what the rendered image
must show.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from lensfit.errors import SpecError
from lensfit.io.specs import load_toml, specs_dir
from synth.lens import (C_LINE_NM, D_LINE_NM, F_LINE_NM, Prescription, Surface, abbe_index, glass_catalogue,
                        load_prescription, paraxial, trace)
from synth.rendering import render
from synth.scene import scene_from_dict

warnings.filterwarnings("ignore", category=DeprecationWarning)

WAVES = (F_LINE_NM, D_LINE_NM, C_LINE_NM)
#: A plano-convex N-BK7 singlet of 50 mm behind a stop 30 mm in front of it: no achromat, so
#: both kinds of colour are large (F and C focus 0.6 and 0.26 mm from d; lateral colour ~1 px).
SINGLET = [{"radius_mm": "inf", "thickness_mm": 30.0, "n": 1.0, "semi_aperture_mm": 1.5, "stop": True},
           {"radius_mm": 25.84, "thickness_mm": 4.0, "glass": "N-BK7", "semi_aperture_mm": 10.0},
           {"radius_mm": "inf", "thickness_mm": 0.0, "n": 1.0, "semi_aperture_mm": 10.0}]


def optiland_material(name):
    from optiland.materials import Material

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Material(name, catalog="schott")


def test_glass_catalogue_matches_an_independent_copy_of_schotts():
    pytest.importorskip("optiland")
    printed = load_toml(specs_dir() / "glasses.toml")["glass"]
    waves = np.array([405.0, F_LINE_NM, 546.07, D_LINE_NM, C_LINE_NM, 706.5])
    for name, glass in glass_catalogue().items():
        theirs = np.array([float(np.ravel(optiland_material(name).n(w * 1e-3))[0]) for w in waves])
        np.testing.assert_allclose(glass.index(waves), theirs, atol=2e-7, err_msg=name)
        assert glass.nd == pytest.approx(printed[name]["nd"], abs=6e-6), name
        assert glass.abbe == pytest.approx(printed[name]["vd"], abs=0.006), name


def test_abbe_law_is_exact_at_d_f_c_and_close_to_crowns_elsewhere():
    """The two-term Cauchy law from n_d and V_d: exact where it is defined, within 2e-4 of the
    Sellmeier curve of every crown of the catalogue from 420 to 700 nm, but not of dense flints."""
    w = np.linspace(420.0, 700.0, 57)
    for name, g in glass_catalogue().items():
        assert abbe_index(g.nd, g.abbe, D_LINE_NM) == pytest.approx(g.nd, abs=1e-12)
        assert (abbe_index(g.nd, g.abbe, F_LINE_NM) - abbe_index(g.nd, g.abbe, C_LINE_NM)
                == pytest.approx(float(g.index(F_LINE_NM) - g.index(C_LINE_NM)), rel=1e-9))
        err = np.abs(abbe_index(g.nd, g.abbe, w) - g.index(w)).max()
        if g.abbe > 50:
            assert err < 2e-4, (name, err)
    flint = glass_catalogue()["N-SF11"]
    assert np.abs(abbe_index(flint.nd, flint.abbe, w) - flint.index(w)).max() > 1e-3


@pytest.mark.parametrize("design", ["cooke-triplet-50", "retrofocus-24"])
def test_efl_per_wavelength_matches_optiland_with_catalogue_glass(design):
    """Each glass surface at its catalogue index (n = the glass's n_d), traced at F, d, C, 450 and
    620 nm: EFL as optiland computes it with its own SCHOTT data, to 1e-8."""
    pytest.importorskip("optiland")
    from optiland import optic

    rx = load_prescription(design)
    rx = Prescription(rx.name, tuple(Surface(s.radius_mm, s.thickness_mm, s.glass.nd if s.glass else s.n,
                                             s.semi_aperture_mm, s.stop, None, s.glass) for s in rx.surfaces))
    bfl = paraxial(rx).bfl_mm
    for w in (*WAVES, 450.0, 620.0):
        lens = optic.Optic()
        lens.surfaces.add(index=0, radius=np.inf, thickness=np.inf)
        n = len(rx.surfaces)
        for i, s in enumerate(rx.surfaces, start=1):
            kw = {"index": i, "radius": s.radius_mm, "thickness": s.thickness_mm if i < n else bfl, "is_stop": s.stop}
            if s.glass is not None:
                kw["material"] = optiland_material(s.glass.name)
            lens.surfaces.add(**kw)
        lens.surfaces.add(index=n + 1)
        lens.set_aperture(aperture_type="EPD", value=paraxial(rx).entrance_pupil_diameter_mm)
        lens.fields.set_type(field_type="angle")
        lens.fields.add(y=0)
        lens.wavelengths.add(value=w * 1e-3, is_primary=True)
        assert paraxial(rx.at_wavelength(w)).efl_mm == pytest.approx(float(lens.paraxial.f2()), rel=1e-8), w


def singlet_scene(waves, *, offset_x_mm=0.0, colour=None, target=None, spp=512, width=200, height=24,
                  focus_plane="best"):
    """``focus_plane = "paraxial"`` puts the sensor at the d line's paraxial image whatever the
    wavelengths, so that scenes with different wavelengths share a camera."""
    lens = {"surface": SINGLET, "f_number": 16.0, "focus_distance_mm": 1000.0, "focus_plane": focus_plane}
    if waves is not None:
        lens["wavelengths_nm"] = list(waves)
    if colour is not None:
        lens["colour"] = colour
    obj = target or {"id": "b", "target": "checkerboard", "squares": [2, 2], "square_mm": 200.0, "distance_mm": 1000.0,
                     "offset_mm": [offset_x_mm, 0.0], "dark": 0.1, "light": 0.9}
    return scene_from_dict({"camera": {"pixel_pitch_mm": 0.01, "width_px": width, "height_px": height},
                            "lens": lens, "render": {"samples_per_pixel": spp, "seed": 3}, "object": [obj]})


def landing_px(cam, rx, point, n=200_000, seed=0, sensor_shift_mm=0.0):
    """Stored-image x (px) where the rays from ``point`` (x, y, depth from the entrance pupil)
    that pass ``rx`` land on the camera's sensor: a forward float64 trace."""
    z_ep = cam.scene_origin_z_mm
    rng = np.random.default_rng(seed)
    r = 0.5 * cam.paraxial.entrance_pupil_diameter_mm * 1.6 * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * math.pi, n)
    src = np.array([point[0], point[1], z_ep - point[2]])
    d = np.stack([r * np.cos(phi), r * np.sin(phi), np.full(n, z_ep)]) - src[:, None]
    d /= np.linalg.norm(d, axis=0)
    start = src[:, None] + ((-1.0 - src[2]) / d[2]) * d
    (x, _, z), (dx, _, dz), passed, _ = trace(rx, tuple(start), tuple(d))
    x_sensor = (x + (cam.sensor_z_mm + sensor_shift_mm - z) / dz * dx)[passed]
    return cam.principal_point_px[0] - x_sensor / cam.pixel_pitch_mm  # the stored image is re-inverted


def test_each_wavelength_images_an_edge_where_and_as_blurred_as_its_rays_land():
    """A vertical edge 100 px off axis, at the distance the d line focuses on (paraxially),
    rendered at F, d and C alone: each image's edge profile is the cumulative distribution of where that
    wavelength's rays from the edge land (absolute position: lateral colour; spread:
    longitudinal colour), with no fitted shift."""
    rows = slice(2, 18)
    probe = singlet_scene([D_LINE_NM], focus_plane="paraxial")
    cam0 = probe.shots[0].camera
    offset = 100.0 * cam0.pixel_pitch_mm * 1000.0 / cam0.sensor_distance_mm
    widths = {}
    for w in WAVES:
        scene = singlet_scene([w], offset_x_mm=offset, width=280, height=48, spp=1024, focus_plane="paraxial")
        cam = scene.shots[0].camera
        img = render(scene).images["shot_000.png"].astype(np.float64)[rows].mean(axis=0)
        row = 0.5 * (rows.start + rows.stop - 1)
        y_obj = (row - cam.principal_point_px[1]) * cam.pixel_pitch_mm * 1000.0 / cam.sensor_distance_mm
        lands = np.sort(landing_px(cam, cam.spectral_cameras()[0].stopped, (offset, y_obj, 1000.0)))
        t = np.arange(cam.width_px, dtype=np.float64)
        u = (np.arange(16) + 0.5) / 16 - 0.5
        esf = np.mean([np.searchsorted(lands, t + du) / len(lands) for du in u], axis=0)
        left, right = img[:150].mean(), img[-15:].mean()
        measured = (img - left) / (right - left)
        assert np.max(np.abs(measured - esf)) < 0.03, (w, np.round(measured - esf, 3))
        widths[w] = (np.std(lands), np.mean(lands))
    # The case must show both kinds of colour clearly.
    assert widths[F_LINE_NM][0] > 2.0 * widths[D_LINE_NM][0]
    assert abs(widths[F_LINE_NM][1] - widths[C_LINE_NM][1]) > 0.5


def test_truth_records_the_colour_the_trace_gives():
    scene = singlet_scene(WAVES)
    cam = scene.shots[0].camera
    t = cam.truth()["lens"]["spectral"]
    assert t["wavelengths_nm"] == list(WAVES) and t["reference_wavelength_nm"] == D_LINE_NM
    # EFL per wavelength: the thick plano-convex lens f = R / (n - 1) (the flat back adds nothing),
    # n the table's n_d moved along the catalogue's dispersion curve.
    glass, n_d = glass_catalogue()["N-BK7"], cam.prescription.surfaces[1].n
    for w, efl in zip(WAVES, t["efl_mm"]):
        n = n_d + float(glass.index(w) - glass.index(D_LINE_NM))
        assert efl == pytest.approx(25.84 / (n - 1.0), rel=1e-9)
    shift = t["focus_shift_mm"]
    assert shift[0] < shift[1] < shift[2] and shift[2] - shift[0] > 0.7  # blue focuses short, red long
    assert cam.truth()["lens"]["best_focus_image_z_mm"] == pytest.approx(cam.sensor_z_mm)
    # Lateral colour: the centroid of the traced spot of a point at the recorded field height.
    field_px = t["lateral_field_height_px"]
    point = (field_px * cam.pixel_pitch_mm * 1000.0 / cam.sensor_distance_mm, 0.0, 1000.0)
    means = [np.mean(landing_px(cam, c.stopped, point, n=400_000)) - cam.principal_point_px[0]
             for c in cam.spectral_cameras()]
    for k in range(3):
        assert t["image_height_px"][k] == pytest.approx(means[k], abs=0.02)
        assert t["lateral_colour_px"][k] == pytest.approx(means[k] - means[1], abs=0.03)


def test_a_spectral_camera_focuses_the_grey_image():
    """Autofocus on a grey image: the sensor sits where the spots of all wavelengths together
    (equal weights) are smallest, not at the d line's focus; a step either way blurs them."""
    cam = singlet_scene(WAVES).shots[0].camera

    def grey_spread(shift):
        return sum(np.var(landing_px(cam, c.stopped, (0.0, 0.0, 1000.0), n=100_000, sensor_shift_mm=shift))
                   for c in cam.spectral_cameras())

    at = grey_spread(0.0)
    assert grey_spread(-0.02) > at and grey_spread(0.02) > at
    d_line = cam.truth()["lens"]["spectral"]["focus_shift_mm"][1]
    assert abs(d_line) > 0.05 and grey_spread(d_line) > 1.05 * at


def test_the_reference_wavelength_alone_is_the_monochrome_render_and_grey_is_the_mean():
    """Only what is called for: wavelengths_nm = [d line] renders bit for bit what no
    wavelengths_nm does; three wavelengths give the mean of the three single renders."""
    plain = render(singlet_scene(None, spp=16)).images["shot_000.png"]
    ref = render(singlet_scene([D_LINE_NM], spp=16)).images["shot_000.png"]
    np.testing.assert_array_equal(plain, ref)
    assert "spectral" not in singlet_scene(None).shots[0].camera.truth()["lens"]
    singles = [render(singlet_scene([w], spp=16, focus_plane="paraxial")).images["shot_000.png"].astype(np.float64)
               for w in WAVES]
    grey = render(singlet_scene(WAVES, spp=16, focus_plane="paraxial")).images["shot_000.png"].astype(np.float64)
    np.testing.assert_allclose(grey, np.mean(singles, axis=0), atol=1e-6)


def test_colour_from_spectral_samples_keeps_white_neutral():
    scene = singlet_scene([465.0, 550.0, 610.0], colour=True, spp=64, width=48, height=32,
                          target={"id": "w", "target": "uniform", "size_mm": [2000.0, 2000.0], "distance_mm": 1000.0,
                                  "value": 0.8})
    img = render(scene).images["shot_000.png"]
    assert img.shape == (32, 48, 3)
    centre = img[8:24, 12:36].reshape(-1, 3).mean(axis=0)
    assert centre == pytest.approx([centre[1]] * 3, rel=2e-3)


SCENE = {"camera": {"pixel_pitch_mm": 0.01, "width_px": 64, "height_px": 48},
         "object": [{"id": "b", "target": "uniform", "size_mm": [100.0, 100.0], "distance_mm": 1000.0}]}


@pytest.mark.parametrize("lens, field, says", [
    ({"focal_length_mm": 50.0, "wavelengths_nm": [500.0]}, "lens.wavelengths_nm", "thin lens has no glass"),
    ({"prescription": "double-gauss-50", "wavelengths_nm": [500.0]}, "lens.wavelengths_nm", "no V or glass"),
    ({"prescription": "cooke-triplet-50", "colour": True}, "lens.colour", "give lens.wavelengths_nm"),
    ({"prescription": "cooke-triplet-50", "wavelengths_nm": [300.0]}, "lens.wavelengths_nm", "minimum of 380"),
    ({"prescription": "cooke-triplet-50", "wavelengths_nm": [500.0, 500.0]}, "lens.wavelengths_nm", "once"),
    ({"prescription": "cooke-triplet-50", "wavelengths_nm": [450.0, 480.0], "colour": True}, "lens.wavelengths_nm",
     "red"),
    ({"surface": [{**SINGLET[0]}, {**SINGLET[1], "glass": "NBK7"}, SINGLET[2]]}, "surface[1].glass",
     "did you mean 'N-BK7'"),
    ({"surface": [SINGLET[0], {**SINGLET[1], "V": 64.0}, SINGLET[2]]}, "surface[1].V", "conflicts with glass"),
    ({"surface": [SINGLET[0], {**SINGLET[1], "n": 1.6}, SINGLET[2]]}, "surface[1].n", "N-BK7 has n_d 1.51680"),
    ({"surface": SINGLET, "prescription": "cooke-triplet-50"}, "lens.surface", "conflicts"),
])
def test_spectral_mistakes_are_refused_naming_the_field(lens, field, says):
    data = {**SCENE, "lens": {"f_number": 16.0, "focus_distance_mm": 1000.0, **lens}}
    with pytest.raises(SpecError) as err:
        scene_from_dict(data)
    assert field in str(err.value) and says in str(err.value), str(err.value)


def test_colour_channels_without_wavelengths_see_the_lens_at_the_d_line():
    """A mosaic or three-wavelength diffraction on a compound lens does not call for a spectral
    render: without wavelengths_nm every channel sees the lens at the d line, as before."""
    scene = scene_from_dict({**SCENE, "lens": {"prescription": "double-gauss-50", "f_number": 8.0,
                                               "focus_distance_mm": 1000.0},
                             "render": {"effects": ["defocus", "diffraction"]},
                             "diffraction": {"wavelength_nm": [610.0, 550.0, 465.0]}})
    assert scene.effects.channels == 3 and scene.shots[0].camera.wavelengths_nm == ()
