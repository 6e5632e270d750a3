"""Internal focusing in synth (``[lens] focusing = "internal"``): a group inside the lens moves,
the sensor stays. Checked against optiland, an independent optics library (a test dependency):
the lens rebuilt there with the group moved by the shift synth found must image the focus
distance (from optiland's own entrance pupil) paraxially onto the fixed sensor, with optiland's
EFL the setting's focal length."""

from __future__ import annotations

import copy
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from lensfit.errors import SpecError
from synth.lens import image_z, internal_focus, load_prescription, paraxial
from synth.scene import scene_from_dict

optiland = pytest.importorskip("optiland")
warnings.filterwarnings("ignore", category=DeprecationWarning)

# design: (the moving group, focus distances as multiples of the EFL), where the group reaches them
CASES = {
    "double-gauss-50": ((6, 10), (20.0, 40.0)),     # rear group, behind the stop
    "telephoto-250": ((4, 6), (6.0, 20.0)),
    "retrofocus-24": ((9, 12), (6.0, 40.0)),
    "cooke-triplet-50": ((0, 2), (40.0,)),          # front cell
}


def optiland_lens(rx, thicknesses, object_distance_mm=None):
    """``rx``'s surfaces in optiland with the axial gaps ``thicknesses`` (the last one: to the
    image plane), the object ``object_distance_mm`` in front of the first vertex (None:
    infinity)."""
    from optiland import optic
    from optiland.materials import IdealMaterial

    lens = optic.Optic()
    lens.surfaces.add(index=0, radius=np.inf, thickness=np.inf if object_distance_mm is None else object_distance_mm)
    for i, (s, t) in enumerate(zip(rx.surfaces, thicknesses), start=1):
        kw = {"index": i, "radius": s.radius_mm, "thickness": t, "is_stop": s.stop}
        if s.n != 1.0:
            kw["material"] = IdealMaterial(n=s.n)
        lens.surfaces.add(**kw)
    lens.surfaces.add(index=len(rx.surfaces) + 1)
    lens.set_aperture(aperture_type="EPD", value=paraxial(rx).entrance_pupil_diameter_mm)
    lens.fields.set_type(field_type="angle")
    lens.fields.add(y=0)
    lens.wavelengths.add(value=0.58756, is_primary=True)
    return lens


@pytest.mark.parametrize("name", list(CASES))
def test_the_moved_group_images_the_focus_distance_on_the_fixed_sensor_as_optiland_traces_it(name):
    group, multiples = CASES[name]
    rx = load_prescription(name).with_f_number(8.0)
    efl = paraxial(rx).efl_mm
    sensor_z = image_z(rx, -math.inf)  # paraxial focus at infinity, the group at its design position
    first, last = group
    efls = []
    for k in multiples:
        X = k * efl
        moved, shift = internal_focus(rx, group, X, sensor_z, focus_plane="paraxial")
        # The same lens built independently: the gap in front of the group longer by the shift, the
        # one behind it shorter; a front group moves the first vertex, and the sensor stays.
        t = [s.thickness_mm for s in rx.surfaces]
        if first > 0:
            t[first - 1] += shift
        if last < len(t) - 1:
            t[last] -= shift
        z_last = float(sum(t[:-1])) + (shift if first == 0 else 0.0)  # the last vertex in the fixed frame
        t[-1] = sensor_z - z_last
        probe = optiland_lens(rx, t, 1e3)
        epl = float(probe.paraxial.EPL())  # the entrance pupil from the first vertex, in optiland
        lens = optiland_lens(rx, t, X - epl)
        y, u = lens.paraxial.marginal_ray()
        y_img = float(np.ravel(y)[-1])
        # the marginal ray from the axial object point crosses the axis on the sensor
        assert abs(y_img) < 1e-6 * paraxial(rx).entrance_pupil_diameter_mm, (name, k, y_img)
        f_optiland = float(lens.paraxial.f2())
        assert paraxial(moved).efl_mm == pytest.approx(f_optiland, rel=1e-9)
        efls.append(f_optiland)
    if len(efls) > 1:
        assert abs(efls[0] / efls[1] - 1) > 1e-3  # the lens breathes: its EFL changes with the focus distance


def bracket_scene(group=(9, 12), near=150.0, far=1000.0):
    return {
        "camera": {"pixel_pitch_mm": 0.01, "width_px": 64, "height_px": 48},
        "lens": {"prescription": "retrofocus-24", "f_number": 5.6, "focus_distance_mm": far,
                 "focusing": "internal", "focus_group": list(group)},
        "render": {"effects": ["defocus"], "method": "raytrace", "samples_per_pixel": 1},
        "object": [{"id": "b", "target": "checkerboard", "squares": [4, 3], "square_mm": 10.0, "distance_mm": 400.0}],
        "shot": [{"setting": "near", "focus_distance_mm": near}, {"setting": "far"}],
    }


def test_an_internally_focused_scene_gives_each_setting_its_own_lens_and_says_so():
    from synth.truth import stack_manifest

    scene = scene_from_dict(bracket_scene())
    near, far = (s.camera for s in scene.shots)
    assert near.focus_group == far.focus_group == (9, 12)
    # The sensor is fixed: where each setting's lens puts it is the same plane (the group behind the
    # stop moves, so the lens coordinates stay put).
    assert near.sensor_z_mm == pytest.approx(far.sensor_z_mm, abs=1e-6)
    for cam in (near, far):
        para = paraxial(cam.prescription)
        assert cam.focal_length_mm == pytest.approx(para.efl_mm, rel=1e-12)
        assert cam.f_number == pytest.approx(para.efl_mm / para.entrance_pupil_diameter_mm, rel=1e-12)
        assert cam.truth()["lens"]["focusing"] == "internal"
    assert near.focal_length_mm != pytest.approx(far.focal_length_mm, rel=1e-3)
    assert near.focus_group_shift_mm != pytest.approx(far.focus_group_shift_mm, abs=1e-3)
    # The stop is the same size in both settings: the aperture ring set at infinity focus.
    stop = [cam.prescription.surfaces[cam.prescription.stop_index].semi_aperture_mm for cam in (near, far)]
    assert stop[0] == pytest.approx(stop[1], rel=1e-9)
    manifest = stack_manifest(scene, ["a.png", "b.png"], ["near", "far"])
    assert manifest["lens"]["focusing"] == "internal"


def test_a_unit_focused_scene_is_unchanged_by_the_new_fields():
    spec = bracket_scene()
    del spec["lens"]["focusing"], spec["lens"]["focus_group"]
    scene = scene_from_dict(spec)
    assert all(s.camera.focus_group is None and s.camera.prescription.name == "retrofocus-24" for s in scene.shots)
    assert scene.shots[0].camera.focal_length_mm == scene.shots[1].camera.focal_length_mm


@pytest.mark.parametrize("change,field", [
    ({"focusing": "internal", "focus_group": None}, "lens.focus_group"),        # internal, no group
    ({"focusing": "unit"}, "lens.focus_group"),                                 # a group without internal
    ({"focus_group": [9, 40]}, "lens.focus_group"),                             # off the lens
    ({"focus_group": [0, 12]}, "lens.focus_group"),                             # the whole lens
    ({"focus_group": [10, 12]}, "lens.focus_group"),                            # splits the element 9-10
    # a double Gauss's rear group meets the stop before it focuses six focal lengths away
    ({"prescription": "double-gauss-50", "focus_group": [6, 10], "focus_distance_mm": 300.0}, "lens.focus_distance_mm"),
])
def test_bad_internal_focusing_is_refused_naming_the_field(change, field):
    spec = copy.deepcopy(bracket_scene())
    for key, value in change.items():
        if value is None:
            spec["lens"].pop(key)
        else:
            spec["lens"][key] = value
    if field == "lens.focus_distance_mm":
        spec["shot"] = [{"setting": "far"}]
    with pytest.raises(SpecError) as err:
        scene_from_dict(spec)
    assert field in str(err.value)


def test_a_thin_lens_refuses_a_focus_group():
    spec = bracket_scene()
    spec["lens"] = {"focal_length_mm": 24.0, "f_number": 5.6, "focus_distance_mm": 1000.0, "focusing": "internal"}
    with pytest.raises(SpecError, match="lens.focusing"):
        scene_from_dict(spec)


def test_a_fit_is_judged_against_each_settings_own_focal_length():
    """The comparison with truth.json (the CLI's truth column, results.json's truth_comparison)
    takes a breathing lens's per-setting EFL, not the one at infinity focus."""
    from types import SimpleNamespace

    from lensfit.fitting.result import Estimate, compare_with_truth

    scene = scene_from_dict(bracket_scene())
    truth = {"focal_length_mm": scene.focal_length_mm,
             "settings": {s.setting: {"focal_length_mm": s.camera.focal_length_mm, "f_number": s.camera.f_number}
                          for s in scene.shots}}
    estimates = {label: {"focal_length_mm": Estimate(t["focal_length_mm"], 0.1, ci95=(t["focal_length_mm"] - 0.2,
                                                                                      t["focal_length_mm"] + 0.2))}
                 for label, t in truth["settings"].items()}
    rows = compare_with_truth(SimpleNamespace(settings=estimates), truth)
    assert {r["setting"] for r in rows} == {"near", "far"}
    assert all(r["relative_error"] == 0.0 and r["within_ci95"] for r in rows)
    assert any(abs(t["focal_length_mm"] / scene.focal_length_mm - 1) > 0.01 for t in truth["settings"].values())


def test_a_compound_lenss_stack_states_its_widest_f_number_as_a_cameras_exif_would(tmp_path):
    """stack.toml's [lens] widest_f_number is the lens file's design f-number (its full aperture),
    or the scene's f-number where the scene opens the lens wider; a thin lens states none."""
    import tomllib

    from synth.truth import stack_manifest

    design = tomllib.loads((Path(__file__).parents[2] / "data_specs" / "lenses" / "retrofocus-24.toml")
                           .read_text())["design_f_number"]
    for f_number, widest in ((1.5 * design, design), (0.9 * design, 0.9 * design)):
        spec = bracket_scene()
        spec["lens"]["f_number"] = f_number
        del spec["lens"]["focusing"], spec["lens"]["focus_group"]
        manifest = stack_manifest(scene_from_dict(spec), ["a.png", "b.png"], ["near", "far"])
        assert manifest["lens"]["widest_f_number"] == pytest.approx(widest, rel=1e-4)
    # The camera's files say it too (EXIF MaxApertureValue), as lensfit init reads it back.
    from lensfit.io.exif import read_camera_record
    from synth.rendering import render
    from synth.stack import write_stack

    spec["render"]["format"] = "jpeg"
    out = write_stack(render(scene_from_dict(spec)), tmp_path / "jpeg")
    assert read_camera_record(out / "shot_000.jpg").widest_f_number == pytest.approx(0.9 * design, abs=0.006)
