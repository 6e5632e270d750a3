"""The real-camera path end to end (``lensfit target`` -> photos -> ``lensfit init`` -> ``fit``),
and ``lensfit init``'s reading of EXIF, grouping and refusals.

The photos are the printed page (the PNG ``lensfit target`` wrote, as an image texture with paper
and ink reflectance) rendered by synth as a camera would store them: JPEG (8-bit sRGB) and DNG
(Bayer mosaic, raw DN), both with EXIF. Only the image files are copied to the photo folder:
``init`` sees what a photographer has. The fit is compared with the truth synth rendered from."""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest

from lensfit.cli import main as lensfit_main
from synth.cli import main as synth_main

from helpers import jpeg_with_exif

SHOTS = [(700.0, (0.0, 0.0), (0.0, 0.0)), (850.0, (25.0, 0.0), (10.0, 0.0)), (1000.0, (0.0, -30.0), (0.0, 0.0)),
         (1300.0, (-20.0, 15.0), (0.0, 0.0)), (1600.0, (0.0, 25.0), (0.0, 0.0)), (2000.0, (0.0, 0.0), (0.0, 0.0)),
         (2200.0, (15.0, -15.0), (0.0, 0.0))]


def camera_scene(fmt: str, f_number: float = 2.8, print_scale: float = 1.0) -> str:
    """A 12 mm lens on a 7.2 x 4.8 mm sensor photographing an A4 print of the board at 0.7-2.2 m,
    focused at 1.3 m; the page printed at ``print_scale`` of its size (a printer's scaling)."""
    effects = '["defocus"]' if fmt == "jpeg" else '["defocus", "mosaic"]'
    text = f"""name = "round-trip"
[camera]
pixel_pitch_mm = 0.008
width_px = 900
height_px = 600
[lens]
focal_length_mm = 12.0
f_number = {f_number}
focus_distance_mm = 1300.0
[render]
effects = {effects}
format = "{fmt}"
samples_per_pixel = 16
[background]
value = 0.3
"""
    text += f"""[[object]]
id = "page"
target = "image"
file = "board.png"
dark = 0.05
light = 0.85
size_mm = [{297.0 * print_scale}, {210.0 * print_scale}]
distance_mm = 1000.0
"""
    for d, tilt, offset in SHOTS:
        text += (f"[[shot]]\npose = [{{ id = \"page\", distance_mm = {d}, tilt_deg = [{tilt[0]}, {tilt[1]}], "
                 f"offset_mm = [{offset[0]}, {offset[1]}] }}]\n")
    return text


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    folder = tmp_path_factory.mktemp("board")
    assert lensfit_main(["target", "--out", str(folder / "board.png"), "--entry", str(folder / "board.toml")]) == 0
    return folder


def photos_of(board: Path, tmp: Path, fmt: str, print_scale: float = 1.0) -> tuple[Path, dict]:
    """Render the scene, copy only the photos to a new folder; returns it and the truth."""
    (tmp / "scene.toml").write_text(camera_scene(fmt, print_scale=print_scale))
    shutil.copy(board / "board.png", tmp / "board.png")
    assert synth_main(["render", str(tmp / "scene.toml"), "--out", str(tmp / "stack")]) == 0
    photos = tmp / "photos"
    photos.mkdir()
    suffix = {"jpeg": ".jpg", "dng": ".dng"}[fmt]
    for p in sorted((tmp / "stack").glob(f"*{suffix}")):
        shutil.copy(p, photos / p.name)
    return photos, json.loads((tmp / "stack" / "truth.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["jpeg", "dng"])
def test_print_photograph_init_fit_recovers_the_lens(board, tmp_path, fmt, capsys):
    photos, truth = photos_of(board, tmp_path, fmt)
    assert lensfit_main(["init", str(photos), "--target", str(board / "board.toml")]) == 0
    manifest = tomllib.loads((photos / "stack.toml").read_text())
    # what init read from the EXIF: the pitch from FocalPlaneXResolution, one setting, the board
    assert manifest["camera"]["pixel_pitch_mm"] == pytest.approx(truth["pixel_pitch_mm"], rel=1e-5)
    assert {im["setting"] for im in manifest["image"]} == {"a"}
    assert manifest["target"][0]["square_mm"] == tomllib.loads((board / "board.toml").read_text())["target"][0][
        "square_mm"]
    assert all(im["x_exif"]["f_number"] == pytest.approx(2.8) for im in manifest["image"])
    assert ("encoding" in manifest["image"][0]) == (fmt == "jpeg")
    out = tmp_path / "results.json"
    code = lensfit_main(["fit", str(photos), "--out", str(out)])
    assert code == 0, capsys.readouterr()
    res = json.loads(out.read_text())
    s = res["settings"]["a"]
    t = truth["settings"]["a"]
    assert res["focal_length_mm"]["value"] == pytest.approx(truth["focal_length_mm"], rel=0.01)
    assert s["f_number"]["value"] == pytest.approx(t["f_number"], rel=0.05)
    assert s["focus_distance_mm"]["value"] == pytest.approx(t["focus_distance_mm"], rel=0.03)
    lo, hi = s["f_number"]["ci95"]
    assert lo < t["f_number"] < hi


def test_a_print_at_97_percent_is_right_once_its_measured_square_is_given(board, tmp_path, capsys):
    """Printers scale: the page printed at 97 % has squares of 29.1 mm. Taken at its drawn size,
    every distance, the focus distance with them, reads 3 % far (and init says to measure); with
    the square measured and given to init, the focus distance is within 0.3 % of the truth."""
    photos, truth = photos_of(board, tmp_path, "jpeg", print_scale=0.97)
    drawn = tomllib.loads((board / "board.toml").read_text())["target"][0]
    focus = truth["settings"]["a"]["focus_distance_mm"]
    errors = {}
    for measured in (None, 0.97 * drawn["square_mm"]):
        extra = [] if measured is None else ["--measured-square-mm", f"{measured:g}"]
        assert lensfit_main(["init", str(photos), "--target", str(board / "board.toml"), "--force", *extra]) == 0
        said = capsys.readouterr().out
        target = tomllib.loads((photos / "stack.toml").read_text())["target"][0]
        out = tmp_path / "results.json"
        assert lensfit_main(["fit", str(photos), "--out", str(out), "--force"]) == 0
        est = json.loads(out.read_text())["settings"]["a"]["focus_distance_mm"]
        errors[measured] = est["value"] / focus - 1
        if measured is None:
            assert "--measured-square-mm" in said and target["square_mm"] == drawn["square_mm"]
        else:
            assert "printed at 97.0 %" in said
            assert target["marker_mm"] == pytest.approx(0.97 * drawn["marker_mm"])
            assert est["ci95"][0] < focus < est["ci95"][1]
    assert 0.02 < errors[None] < 0.045
    assert abs(errors[0.97 * drawn["square_mm"]]) < 0.003


@pytest.mark.parametrize("measured", ["3", "300", "nan"])
def test_a_measured_square_far_from_the_drawn_one_is_refused(board, tmp_path, capsys, measured):
    photos = tmp_path / "photos"
    photos.mkdir()
    jpeg_with_exif(photos / "a.jpg", plane_res=1000.0, plane_unit=4)
    assert lensfit_main(["init", str(photos), "--target", str(board / "board.toml"),
                         "--measured-square-mm", measured]) == 2
    err = capsys.readouterr().err
    assert "--measured-square-mm" in err and len(err.strip().splitlines()) == 1
    assert not (photos / "stack.toml").exists()


# --------------------------------------------------------------------------- init's reading, grouping, refusals


def test_exif_fields_in_lensfit_units(tmp_path):
    from lensfit.io.exif import read_camera_record

    # 2000 px/inch -> 0.0127 mm; SubjectDistance 1.5 m; Make repeated in Model shown once
    r = read_camera_record(jpeg_with_exif(tmp_path / "a.jpg", subject_m=1.5, plane_res=2000.0, plane_unit=2))
    assert (r.focal_length_mm, r.f_number, r.focus_distance_mm) == (50.0, 2.8, 1500.0)
    assert r.focal_plane_pitch_mm == pytest.approx(25.4 / 2000.0)
    assert r.camera == "Canon EOS R5"
    r = read_camera_record(jpeg_with_exif(tmp_path / "b.jpg", model="D850", make="NIKON CORPORATION",
                                          plane_res=1000.0, plane_unit=3))
    assert r.focal_plane_pitch_mm == pytest.approx(0.01) and r.focus_distance_mm is None
    assert r.camera == "NIKON CORPORATION D850"
    (tmp_path / "c.jpg").write_bytes(b"not an image")
    assert read_camera_record(tmp_path / "c.jpg").f_number is None


def test_the_lenss_widest_f_number_from_exif_goes_into_the_draft(tmp_path):
    """MaxApertureValue is an APEX value, N = 2 ** (Av / 2): the published table's Av 1, 3, 5 are
    f/1.4, f/2.8, f/5.6. A prime's LensSpecification serves where it is missing, a zoom's does not
    (its widest f-number depends on the focal length). lensfit init writes it into [lens]."""
    from lensfit.io.exif import read_camera_record

    for av, n in ((1.0, 1.4), (3.0, 2.8), (5.0, 5.6)):
        r = read_camera_record(jpeg_with_exif(tmp_path / f"av{av}.jpg", max_aperture_apex=av))
        assert r.widest_f_number == pytest.approx(n, abs=0.07)
    assert read_camera_record(jpeg_with_exif(tmp_path / "prime.jpg", lens_spec=(50, 50, 1.8, 1.8))).widest_f_number \
        == pytest.approx(1.8)
    assert read_camera_record(jpeg_with_exif(tmp_path / "zoom.jpg", lens_spec=(24, 70, 2.8, 4))).widest_f_number is None
    assert read_camera_record(jpeg_with_exif(tmp_path / "none.jpg")).widest_f_number is None
    photos = tmp_path / "p"
    photos.mkdir()
    for i, n in enumerate((2.8, 5.6)):
        jpeg_with_exif(photos / f"img_{i}.jpg", fnum=n, subject_m=1.5, max_aperture_apex=2.0)
    assert lensfit_main(["init", str(photos)]) == 0
    m = tomllib.loads((photos / "stack.toml").read_text())
    assert m["lens"] == {"widest_f_number": 2.0}


def test_exif_is_read_from_the_files_head_and_maker_notes_only_for_canon(tmp_path, monkeypatch):
    """A maker note of 100 MB (or one claiming 2 GB) kept exifread busy for minutes: the EXIF is
    parsed from the file's first EXIF_READ_BYTES without maker notes, and only a Canon body's
    (its focus distance) from the first MAKER_NOTE_READ_BYTES; what the EXIF says still comes out."""
    import exifread

    from lensfit.io import exif

    calls = []
    original = exifread.process_file

    def spy(fh, **kw):
        calls.append((kw.get("details"), len(fh.getbuffer())))
        return original(fh, **kw)

    monkeypatch.setattr(exifread, "process_file", spy)
    big = jpeg_with_exif(tmp_path / "n.jpg", make="NIKON CORPORATION", model="D850", focal=85.0)
    with big.open("ab") as fh:  # a file far larger than its EXIF (bytes after the JPEG's end)
        fh.write(bytes(12 << 20))
    r = exif.read_camera_record(big)
    assert r.focal_length_mm == 85.0 and calls == [(False, exif.EXIF_READ_BYTES)]
    calls.clear()
    r = exif.read_camera_record(jpeg_with_exif(tmp_path / "c.jpg"))  # Canon, no SubjectDistance
    assert r.focal_length_mm == 50.0 and [d for d, _ in calls] == [False, True]
    assert all(n <= exif.MAKER_NOTE_READ_BYTES for d, n in calls if d)


def test_init_groups_by_f_number_and_focus_and_takes_pitch_from_the_camera_table(tmp_path, capsys):
    photos = tmp_path / "p"
    photos.mkdir()
    for i, (n, d) in enumerate([(2.8, 1.5), (2.8, 1.5), (5.6, 1.5), (2.8, 3.0)]):
        jpeg_with_exif(photos / f"img_{i}.jpg", fnum=n, subject_m=d)
    assert lensfit_main(["init", str(photos)]) == 0
    m = tomllib.loads((photos / "stack.toml").read_text())
    assert [im["setting"] for im in m["image"]] == ["a", "a", "b", "c"]
    # Canon EOS R5: 36.0 mm wide (data_specs/cameras.toml) over the 64 px image width
    assert m["camera"] == {"sensor_width_mm": 36.0}
    assert [im["encoding"] for im in m["image"]] == ["srgb"] * 4
    assert "assumed the board" in capsys.readouterr().out
    # a second run does not replace it; --force replaces what init wrote, never a user's file
    assert lensfit_main(["init", str(photos)]) == 2
    assert lensfit_main(["init", str(photos), "--force", "--settings", "per-image"]) == 0
    assert [im["setting"] for im in tomllib.loads((photos / "stack.toml").read_text())["image"]] == list("abcd")
    (photos / "stack.toml").write_text("# my own\n")
    assert lensfit_main(["init", str(photos), "--force"]) == 2
    assert (photos / "stack.toml").read_text() == "# my own\n"


def test_init_pitch_of_a_resized_copy_and_raw_jpeg_pairs(tmp_path):
    photos = tmp_path / "p"
    photos.mkdir()
    # the EXIF resolution refers to a 6400 px wide original; this copy is 64 px wide: pitch x 100
    jpeg_with_exif(photos / "x.jpg", model="Unknown body", plane_res=1000.0, plane_unit=3, exif_width=6400)
    assert lensfit_main(["init", str(photos)]) == 0
    assert tomllib.loads((photos / "stack.toml").read_text())["camera"]["pixel_pitch_mm"] == pytest.approx(1.0)
    from lensfit.io.manifest import photo_files

    (photos / "x.dng").write_bytes(b"")
    (photos / "y.png").write_bytes(b"")
    (photos / "notes.txt").write_text("")
    assert [p.name for p in photo_files(photos)[0]] == ["x.dng", "y.png"]
    assert [p.name for p in photo_files(photos, "jpeg")[0]] == ["x.jpg", "y.png"]


@pytest.mark.parametrize("case, needle", [
    ("no-pitch", "--pixel-pitch MM"),
    ("two-focal-lengths", "one focal length"),
    ("two-sizes", "images of one size"),
    ("empty", "PHOTOS_DIR"),
    ("two-pitches", "--sensor-width must be given alone"),
    ("bad-target", "no [[target]] tables"),
])
def test_init_refusals_name_the_fix(tmp_path, capsys, case, needle):
    photos = tmp_path / "p"
    photos.mkdir()
    args = ["init", str(photos)]
    if case == "no-pitch":
        jpeg_with_exif(photos / "a.jpg", make="Acme", model="Nonesuch 1")
    elif case == "two-focal-lengths":
        jpeg_with_exif(photos / "a.jpg", focal=24.0)
        jpeg_with_exif(photos / "b.jpg", focal=70.0)
    elif case == "two-sizes":
        jpeg_with_exif(photos / "a.jpg")
        jpeg_with_exif(photos / "b.jpg", size=(40, 64))
    elif case == "two-pitches":
        jpeg_with_exif(photos / "a.jpg")
        args += ["--pixel-pitch", "0.005", "--sensor-width", "36"]
    elif case == "bad-target":
        jpeg_with_exif(photos / "a.jpg")
        (tmp_path / "t.toml").write_text("[camera]\npixel_pitch_mm = 0.005\n")
        args += ["--target", str(tmp_path / "t.toml")]
    assert lensfit_main(args) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1
    assert not (photos / "stack.toml").exists()


def test_focus_distance_from_canon_maker_note_and_infinity():
    from lensfit.io.exif import record_from_tags

    # exifread's names: Canon's ShotInfo SubjectDistance is in centimetres
    r = record_from_tags({"Image Make": "Canon", "EXIF FocalLength": 35.0, "MakerNote SubjectDistance": 250})
    assert (r.focus_distance_mm, r.focus_distance_source) == (2500.0, "Canon maker note")
    # EXIF SubjectDistance wins; 0xFFFFFFFF means infinity, 0 means unknown
    r = record_from_tags({"EXIF SubjectDistance": 4294967295.0, "MakerNote SubjectDistance": 250})
    assert r.focus_distance_mm == float("inf")
    assert record_from_tags({"EXIF SubjectDistance": 0.0}).focus_distance_mm is None


def test_a_raw_files_thumbnail_width_is_not_the_pitchs_reference():
    from lensfit.io.exif import record_from_tags

    # NEF-style: IFD0 is a 160 px thumbnail; the pitch must not be rescaled to it
    r = record_from_tags({"Image ImageWidth": 160, "EXIF FocalPlaneXResolution": 1000.0,
                          "EXIF FocalPlaneResolutionUnit": 3})
    assert r.focal_plane_pitch_mm == pytest.approx(0.01) and r.reference_width_px is None


def test_hostile_photo_folders_cannot_write_toml_or_reach_outside(tmp_path, capsys):
    """File names and EXIF reach stack.toml only through a TOML writer and the terminal only
    escaped: a name holding a newline and a TOML table stays a file name, an escape sequence is
    shown as text, an emoji in the camera's name writes valid TOML; a link that leads out of the
    folder is refused, naming it."""
    photos = tmp_path / "p"
    photos.mkdir()
    jpeg_with_exif(photos / "a.jpg", make="Canon", model="Canon EOS R5 \U0001F4F7")
    jpeg_with_exif(photos / 'b\n[[intrinsics]]\nsetting = "a"\nfocal_length_px = 1.jpg')
    jpeg_with_exif(photos / "c\x1b[31m.jpg")
    args = ["init", str(photos), "--pixel-pitch", "0.005"]
    (photos / "x.jpg").symlink_to("/etc/passwd")
    assert lensfit_main(args) == 2
    err = capsys.readouterr().err
    assert "x.jpg" in err and "/etc/passwd" in err and len(err.strip().splitlines()) == 1
    (photos / "x.jpg").unlink()
    assert lensfit_main(args) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\\x1b" in out
    manifest = tomllib.loads((photos / "stack.toml").read_text())
    assert "intrinsics" not in manifest
    assert sorted(im["file"] for im in manifest["image"])[1].startswith("b\n[[intrinsics]]")
    assert any("Canon EOS R5" in im.get("x_exif", {}).get("camera", "") for im in manifest["image"])


def test_portrait_photos_are_turned_back_and_fit_as_the_landscape_ones(calibration_stack, tmp_path, capsys):
    """Photos whose pixels were turned to portrait (an export that applied the EXIF orientation):
    ``lensfit init`` writes rotate_deg = 90 for them, says so, and the stack reads exactly the
    pixels of the sensor: the fit equals the fit of the untouched photos."""
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    for k, png in enumerate(sorted(calibration_stack.glob("*.png"))):
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(photos / png.name), np.rot90(raw, -1) if k in (2, 5) else raw)  # turned clockwise
    assert lensfit_main(["init", str(photos), "--pixel-pitch", "0.006"]) == 0
    out = capsys.readouterr().out
    assert "2 portrait photo(s)" in out and "rotate_deg = 90" in out
    manifest = tomllib.loads((photos / "stack.toml").read_text())
    assert [im.get("rotate_deg", 0) for im in manifest["image"]] == [0, 0, 90, 0, 0, 90, 0, 0]
    from lensfit.io.stack import load_stack

    turned, original = load_stack(photos), load_stack(calibration_stack)
    for k in range(8):
        assert np.array_equal(turned.read(k), original.read(k))


def test_init_names_settings_past_zz_and_refuses_more_photos_than_a_stack_lists(tmp_path, capsys):
    """Per-image settings past 702 photos are labelled as spreadsheet columns (a..z, aa..zz,
    aaa, ...; an internal error before), and a folder of more photos than a stack may list is
    refused before any is opened."""
    import itertools
    import shutil
    import string

    from lensfit.io.stack import MAX_IMAGES

    photos = tmp_path / "p"
    photos.mkdir()
    seed = jpeg_with_exif(tmp_path / "seed.jpg")
    for k in range(703):
        shutil.copyfile(seed, photos / f"p{k:05d}.jpg")
    assert lensfit_main(["init", str(photos), "--settings", "per-image"]) == 0
    labels = [im["setting"] for im in tomllib.loads((photos / "stack.toml").read_text())["image"]]
    columns = ["".join(t) for n in (1, 2, 3) for t in itertools.product(string.ascii_lowercase, repeat=n)]
    assert labels == columns[:703]
    many = tmp_path / "many"
    many.mkdir()
    for k in range(MAX_IMAGES + 1):
        (many / f"p{k:05d}.jpg").write_bytes(b"not opened")
    capsys.readouterr()
    assert lensfit_main(["init", str(many)]) == 2
    err = capsys.readouterr().err
    assert f"at most {MAX_IMAGES}" in err and len(err.strip().splitlines()) == 1
