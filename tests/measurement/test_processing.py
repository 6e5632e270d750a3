"""Developed images (lensfit.measurement.processing): a camera's or a raw developer's tone curve and sharpening
read N high; the EXIF and halos on the edges say so, and the f-number is refused with the fix,
while faithful sRGB JPEGs and linear images keep their reading."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from lensfit.estimators.halo import halo_amounts, pooled
from lensfit.measurement.measure import Measurement
from lensfit.measurement.pipeline import measure_and_fit
from lensfit.measurement.processing import DEVELOPERS, from_exif
from lensfit.io.images import read_image
from lensfit.io.stack import load_stack


def _encode(linear):
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)


def _jpeg_copy(stack, folder, develop=None, software=None):
    """``stack``'s PNGs as 8-bit sRGB JPEGs in ``folder``; ``develop`` maps the encoded image
    (float, 0-1) as a camera would; ``software``: the EXIF Software tag written."""
    folder.mkdir()
    for png in sorted(stack.glob("*.png")):
        encoded = _encode(read_image(png))
        if develop is not None:
            encoded = develop(encoded)
        exif = Image.Exif()
        if software:
            exif[0x0131] = software
        Image.fromarray(np.round(255 * np.clip(encoded, 0, 1)).astype(np.uint8)).save(
            folder / f"{png.stem}.jpg", quality=95, exif=exif)
    (folder / "stack.toml").write_text((stack / "stack.toml").read_text().replace(".png", ".jpg")
                                       .replace('encoding = "linear"', 'encoding = "srgb"'))
    return folder


def _camera(encoded):
    """An in-camera pipeline's look: an S curve over the encoded values and a 1 px unsharp mask of
    amount 0.5 (a typical default)."""
    curved = 0.8 * encoded
    curved = curved - 0.04 * np.sin(2 * np.pi * curved)
    blurred = cv2.GaussianBlur(curved, (0, 0), 1.0)
    return curved + 0.5 * (curved - blurred)


def _sharpened(encoded):
    """A 1 px unsharp mask of amount 0.6, with headroom for its overshoot."""
    encoded = 0.8 * encoded
    return encoded + 0.6 * (encoded - cv2.GaussianBlur(encoded, (0, 0), 1.0))


def test_halos_are_read_from_sharpened_edges_and_not_from_a_lens(calibration_stack, tmp_path):
    """The pooled unsharp-mask amount of a sharpened copy of a stack is well above 0, that of the
    stack as the lens drew it within noise of 0 (the lens's PSF is never negative)."""
    sharp_dir = _jpeg_copy(calibration_stack, tmp_path / "sharp", _sharpened)
    found = {}
    for name, folder in (("plain", calibration_stack), ("sharp", sharp_dir)):
        measurement = Measurement(folder, keep_profiles=True)
        measurement.read()
        state = measurement.profiles["state"]
        a, v = halo_amounts(state[7], [state[1][i] for i in state[8]])
        found[name] = pooled(a, v)
    assert abs(found["plain"][0]) < 0.03, found
    assert found["sharp"][0] > 0.2 and found["sharp"][0] > 10 * found["sharp"][1], found


def test_a_developed_stack_refuses_n_with_the_cause_and_keeps_f_and_focus(calibration_stack, tmp_path):
    """An in-camera look (S curve, unsharp mask) with no EXIF at all: the halos alone refuse the
    f-number, naming sharpening and the fix; f and the focus distance stay right. Reported
    anyway (``processed="report"``), a warning says so."""
    truth = json.loads((calibration_stack / "truth.json").read_text())
    folder = _jpeg_copy(calibration_stack, tmp_path / "camera", _camera)
    _, result, _ = measure_and_fit(folder)
    n = result.settings["a"]["f_number"]
    assert n.value is None and "sharpening halos" in n.reason and "RAW" in n.reason
    assert result.settings["a"]["aperture_diameter_mm"].value is None
    assert result.processing.halos and result.processing.developer is None
    doc = result.to_json_dict()
    assert doc["processing"]["f_number_biased"] and doc["settings"]["a"]["f_number"]["value"] is None
    lo, hi = result.focal_length_mm.ci95
    assert lo <= truth["focal_length_mm"] <= hi
    lo, hi = result.settings["a"]["focus_distance_mm"].ci95
    assert lo <= truth["settings"]["a"]["focus_distance_mm"] <= hi
    _, reported, _ = measure_and_fit(folder, processed="report")
    assert any("sharpening halos" in w and "--processed report" in w for w in reported.warnings)
    assert reported.processing.halos


def test_exif_names_the_developer_and_linear_images_are_trusted(calibration_stack, tmp_path):
    """A Software tag naming a raw developer marks sRGB images as developed (even without halos);
    the same files declared linear, as a linear export would be, are trusted; a faithful sRGB
    JPEG with no EXIF is not marked."""
    folder = _jpeg_copy(calibration_stack, tmp_path / "dt", software="darktable 4.2.1")
    found = from_exif(load_stack(folder))
    assert found.developer == "darktable 4.2.1" and found.biases_f_number and len(found.developed_files) == 8
    (folder / "stack.toml").write_text((folder / "stack.toml").read_text().replace('"srgb"', '"linear"'))
    assert not from_exif(load_stack(folder)).biases_f_number
    faithful = _jpeg_copy(calibration_stack, tmp_path / "faithful")
    _, result, _ = measure_and_fit(faithful)
    assert not result.processing.biases_f_number and result.settings["a"]["f_number"].value is not None


@pytest.mark.parametrize("make, software, developed", [
    ("lensfit", "darktable 4.2.1", True),  # synth's DNG developed by darktable (it keeps the Make)
    ("lensfit", "", False), ("lensfit", "lensfit synth", False),  # synth's own JPEG
    ("Canon", "", True), ("Canon", "RawTherapee 5.9", True)])
def test_a_developer_is_named_whatever_camera_made_the_raw(tmp_path, make, software, developed):
    from lensfit.io.exif import CameraRecord
    from lensfit.measurement.processing import developer_of

    record = CameraRecord(make=make, model=f"{make} body", software=software or None)
    assert bool(developer_of(tmp_path / "a.jpg", record)) == developed
    assert developer_of(tmp_path / "a.dng", record) is None  # a raw file is what the sensor gave


@pytest.mark.parametrize("software, developer", [
    ("darktable 4.2.1", True), ("RawTherapee 5.9", True), ("Adobe Photoshop Lightroom Classic 13.1", True),
    ("Capture One 23 Windows", True), ("DxO PhotoLab 7", True), ("ART 1.21", True),
    ("Ver.1.00", False), ("Canon EOS R5 firmware", False), ("Blender 4.1", False)])
def test_developer_names(software, developer):
    assert bool(DEVELOPERS.search(software)) == developer


def test_init_notes_developed_photos(calibration_stack, tmp_path):
    """``lensfit init`` on a camera's JPEGs says they were developed and what to give instead;
    on lensfit's own faithful JPEGs it says nothing of the kind."""
    from lensfit.io.manifest import draft_manifest

    folder = tmp_path / "photos"
    folder.mkdir()
    for k, png in enumerate(sorted(calibration_stack.glob("*.png"))[:3]):
        exif = Image.Exif()
        exif[0x010F], exif[0x0110], exif[0x0131] = "Canon", "Canon EOS R5", "Firmware Version 1.8.1"
        Image.fromarray(np.round(255 * _encode(read_image(png))).astype(np.uint8)).save(
            folder / f"IMG_{k}.jpg", quality=95, exif=exif)
    notes = " ".join(draft_manifest(folder, pixel_pitch_mm=0.006).notes)
    assert "3 photo(s) were developed (in-camera JPEG of the Canon EOS R5" in notes and "RAW" in notes
    faithful = _jpeg_copy(calibration_stack, tmp_path / "faithful", software="lensfit synth")
    (faithful / "stack.toml").unlink()
    assert "developed" not in " ".join(draft_manifest(faithful, pixel_pitch_mm=0.006).notes)


@pytest.mark.parametrize("name, developer, keeps_pitch", [
    ("rawtherapee-5.9_shot_000.jpg", "RawTherapee 5.9", False), ("darktable-4.2.1_shot_000.jpg", "darktable 4.2.1", True)])
def test_files_written_by_the_developers_name_them(tmp_path, capsys, name, developer, keeps_pitch):
    """JPEGs written by RawTherapee and darktable themselves (tests/fixtures/developed/README.md)
    from synth's DNG, whose Make reads lensfit: the developer is named; where the developer
    dropped the focal-plane resolution, lensfit init asks for the pixel pitch."""
    import shutil
    from pathlib import Path

    from lensfit.cli import main
    from lensfit.io.exif import read_camera_record
    from lensfit.measurement.processing import developer_of

    path = Path(__file__).resolve().parents[1] / "fixtures" / "developed" / name
    record = read_camera_record(path)
    assert record.make == "lensfit" and developer_of(path, record) == developer
    assert (record.focal_plane_pitch_mm is not None) == keeps_pitch
    photos = tmp_path / "photos"
    photos.mkdir()
    shutil.copy(path, photos / "shot_000.jpg")
    code = main(["init", str(photos)])
    said = capsys.readouterr()
    if keeps_pitch:
        assert code == 0 and "developed" in said.out and developer in said.out
    else:
        assert code == 2 and "--pixel-pitch" in said.err


def test_a_tone_curve_the_declared_encoding_does_not_undo_is_named_and_refuses_n(calibration_stack, tmp_path):
    """The same sRGB JPEGs declared sRGB (right) and linear (an sRGB curve left in the edges): the
    target's corners stay where they are under any monotone curve, and in linear light the
    edges lie on the lines through them (the offset within a few thousandths of a blur radius);
    with the sRGB curve left in, every edge moves toward its dark side (the curve lifts the
    midtones), which names the mismatch and refuses N, keeping f and the focus distance."""
    from lensfit.measurement.processing import TONE_MIN_OFFSET

    right = _jpeg_copy(calibration_stack, tmp_path / "right")
    _, result, _ = measure_and_fit(right)
    tone = result.processing
    assert tone.tone_edges >= 20 and abs(tone.tone_offset) < TONE_MIN_OFFSET / 3, tone
    assert not tone.tone_mismatch and result.settings["a"]["f_number"].value is not None
    wrong = tmp_path / "wrong"
    shutil.copytree(right, wrong)
    (wrong / "stack.toml").write_text((wrong / "stack.toml").read_text().replace('"srgb"', '"linear"'))
    _, result, _ = measure_and_fit(wrong)
    tone = result.processing
    assert tone.tone_mismatch and tone.tone_offset < -TONE_MIN_OFFSET, tone
    n = result.settings["a"]["f_number"]
    assert n.value is None and "declared encoding (linear)" in n.reason and 'encoding = "srgb"' in n.reason
    # the model's curve warps the declared encoding (here none) with a few sine terms, which do not
    # hold the sRGB curve's steep start: it says why it does not read N
    why = result.processing.model["why"]
    assert why and why in n.reason and not result.processing.modelled, why
    assert result.focal_length_mm.value is not None and result.settings["a"]["focus_distance_mm"].value is not None


@pytest.fixture(scope="module")
def fast_stack(tmp_path_factory):
    """The calibration stack's scene at f/2.8 (Airy pattern 0.26 px at 550 nm, which the
    processing model holds)."""
    from helpers import calibration_scene
    from synth.rendering import render
    from synth.scene import scene_from_dict
    from synth.stack import write_stack

    scene = calibration_scene()
    scene["lens"]["f_number"] = 2.8
    out = tmp_path_factory.mktemp("fast") / "calib"
    write_stack(render(scene_from_dict(scene)), out)
    return out


def _developed(encoded):
    """A developer's look, by OpenCV and numpy: +0.5 EV with a highlight shoulder (Reinhard's
    curve) on the linear values, sRGB-encoded, then a 1 px unsharp mask of amount 0.5."""
    light = np.where(encoded <= 0.04045, encoded / 12.92, ((np.clip(encoded, 0, 1) + 0.055) / 1.055) ** 2.4)
    curved = _encode(1.4 * light / (1.0 + 0.7 * light))
    return curved + 0.5 * (curved - cv2.GaussianBlur(curved, (0, 0), 1.0))


def test_the_processing_model_reads_n_through_a_curve_and_mask_it_was_not_given(fast_stack, tmp_path):
    """JPEGs through a developer-like curve (not of the model's sine family) and an unsharp mask: the
    plain readings refuse N (``processed="refuse"``); the model (the default) finds the mask it
    was made with and reads N within 2.5 % of the truth rendered (+1.99 % with OpenCV 5.0, whose
    JPEG codec wrote the images, +2.03 % with 5.1), inside its 95 % interval, f and the focus
    distance too."""
    truth = json.loads((fast_stack / "truth.json").read_text())["settings"]["a"]
    folder = _jpeg_copy(fast_stack, tmp_path / "developed", _developed)
    _, refused, _ = measure_and_fit(folder, processed="refuse")
    assert refused.settings["a"]["f_number"].value is None
    samples, result, _ = measure_and_fit(folder)
    found = result.processing
    assert found.modelled and not found.biases_f_number, found.model.get("why")
    assert 0.3 < found.model["sharpening_amount"] < 0.7 and 0.7 < found.model["sharpening_sigma_px"] < 1.4
    n = result.settings["a"]["f_number"]
    assert abs(n.value / truth["f_number"] - 1) < 0.025, n
    assert n.ci95[0] <= truth["f_number"] <= n.ci95[1], n
    assert n.shares and n.shares.get("processing", 0) > 0
    focus = result.settings["a"]["focus_distance_mm"]
    assert focus.ci95[0] <= truth["focus_distance_mm"] <= focus.ci95[1]
    assert any("tone curve and sharpening fitted" in w for w in result.warnings)
    assert all("processing_modelled" in s.flags for s in samples.samples if s.coc_diameter_px is not None)
    doc = result.to_json_dict()["processing"]
    assert doc["f_number_modelled"] and not doc["f_number_biased"] and len(doc["model"]["tone_curve"]) == 21


def test_n_read_through_the_model_carries_the_error_of_its_form(camera_raw_stack, tmp_path):
    """A camera's JPEG engine the model holds only approximately: LibRaw's demosaic and encoding
    (BT.709's curve, declared sRGB), an S curve, a wide weak unsharp mask (1.5 px, amount 0.5),
    4:2:0 JPEG. The model finds the mask, yet reads N 1.5 % low, where its parameters'
    covariance says 0.3 %: the interval holds the truth (its 95 % reaching 0.7 % above it) only
    with the form's error carried."""
    from lensfit.bench.developed import in_camera
    from lensfit.measurement.processing import MODEL_FORM_SIGMA

    folder = tmp_path / "jpeg"
    in_camera(sorted(camera_raw_stack.glob("*.dng")), folder, usm_sigma_px=1.5, usm_amount=0.5)
    (folder / "stack.toml").write_text((camera_raw_stack / "stack.toml").read_text().replace('.dng"', '.jpg"')
                                       .replace('encoding = "linear"', 'encoding = "srgb"'))
    truth = json.loads((camera_raw_stack / "truth.json").read_text())["settings"]["a"]["f_number"]
    _, result, _ = measure_and_fit(folder)
    n = result.settings["a"]["f_number"]
    assert result.processing.modelled, result.processing.model
    assert 0.3 < result.processing.model["sharpening_amount"] < 0.8
    assert 1.2 < result.processing.model["sharpening_sigma_px"] < 1.8
    assert n.sigma / n.value >= MODEL_FORM_SIGMA and n.shares.get("processing", 0) > 0
    assert n.ci95[0] <= truth <= n.ci95[1], (n, truth)


def test_noise_reduction_before_the_mask_is_refused_not_read(camera_raw_stack, tmp_path):
    """A camera's JPEG engine that smooths before it sharpens (non-local means, then the mask): an
    edge-preserving filter is no tone curve or unsharp mask, and the model misses the profiles
    beyond their noise. N is refused, saying why and what to give instead; f and the focus
    distance, which do not rest on the blur's scale, hold their truth."""
    from lensfit.bench.developed import DENOISE_H, in_camera

    folder = tmp_path / "jpeg"
    in_camera(sorted(camera_raw_stack.glob("*.dng")), folder, denoise_h=DENOISE_H)
    (folder / "stack.toml").write_text((camera_raw_stack / "stack.toml").read_text().replace('.dng"', '.jpg"')
                                       .replace('encoding = "linear"', 'encoding = "srgb"'))
    truth = json.loads((camera_raw_stack / "truth.json").read_text())
    _, result, _ = measure_and_fit(folder)
    n = result.settings["a"]["f_number"]
    assert n.value is None and not result.processing.modelled
    assert "noise reduction" in n.reason and "RAW" in n.reason, n.reason
    f, focus = result.focal_length_mm, result.settings["a"]["focus_distance_mm"]
    assert f.ci95[0] <= truth["focal_length_mm"] <= f.ci95[1]
    assert focus.ci95[0] <= truth["settings"]["a"]["focus_distance_mm"] <= focus.ci95[1]


def test_a_tone_curves_shift_of_the_edges_is_taken_off_the_lines_that_place_the_corners():
    """A tone curve the declared encoding does not undo moves every edge toward its bright side by
    a share of its blur (here 0.15 of each radius, radii 1-6 px across a board tilted in depth).
    Corners placed where the edge lines meet move with them wherever the edges meeting there
    differ in side or blur (the rim, and across the blur's gradient), and the focal length with
    the corners. The pooled shift is read back from the lines against the saddle corners and taken
    off them: every corner lands on the truth; a shift the tone test does not name (0.02 of a
    radius) is left alone, and images of another declared encoding are pooled apart."""
    from types import SimpleNamespace

    from lensfit.calibration.camera import Intrinsics
    from lensfit.calibration.targets import Detection, Target
    from lensfit.estimators.base import EdgeTask
    from lensfit.measurement.edge_geometry import refined_detections, tone_shift, tone_shifts

    target = Target({"id": "board", "kind": "checkerboard", "squares": [10, 7], "square_mm": 20.0})
    obj = target.inner_corners_mm()
    true = 200.0 + 12.0 * obj[:, :2] + 0.004 * obj[:, :2] ** 2  # (a perspective-like stretch)
    intr = Intrinsics(1000.0, (600.0, 400.0), (0.0, 0.0, 0.0, 0.0, 0.0), 0.1, 1, "calibrated")
    rng = np.random.default_rng(4)

    def first_pass(share):
        tasks, meta, ests = [], [], []
        for k, seg in enumerate(target.edges()):
            a, b = true[seg.corner_ids[0]], true[seg.corner_ids[1]]
            t = (b - a) / np.linalg.norm(b - a)
            bright = np.array([-t[1], t[0]]) * (1 if (seg.corner_ids[0] + k) % 3 else -1)
            coc = 2.0 + 10.0 * (a[0] - true[:, 0].min()) / np.ptp(true[:, 0])  # blur grows across the board
            step = share * 0.5 * coc * bright
            tasks.append(EdgeTask(a, b, 10.0, 10.0))
            meta.append(("board", seg, None, None))
            ests.append(SimpleNamespace(line_px=(a + step, b + step), bright_side=tuple(bright), coc_diameter_px=coc,
                                        line_cov_px2=(1e-4, -5e-5, 1e-4)))
        return tasks, meta, ests

    rough = Detection("board", obj, true + rng.normal(0, 0.1, true.shape), np.arange(len(obj)))
    first = first_pass(0.15)
    shift = tone_shift({0: first}, {"board": target})
    assert shift == pytest.approx(0.15, abs=1e-9)
    plain = refined_detections([rough], first, intr, {"board": target})[0].image_points_px
    moved = refined_detections([rough], first, intr, {"board": target}, shift_radii=shift)[0].image_points_px
    assert np.abs(plain - true).max() > 0.2  # the rim's corners, by a share of their blur
    assert np.abs(moved - true).max() < 1e-6
    assert tone_shift({0: first_pass(0.02)}, {"board": target}) == 0.0
    # a RAW file beside the JPEGs keeps its lines: the shift is pooled per declared encoding
    got = tone_shifts({0: first, 1: first_pass(0.0), 2: first}, ["srgb", "linear", "srgb"], {"board": target})
    assert got == pytest.approx({0: 0.15, 1: 0.0, 2: 0.15}, abs=1e-9)
    assert tone_shifts({0: first}, ["linear"], {"board": target}) == {0: 0.0}  # (declared linear: the lens's lines)
    squares = Target({"id": "board", "kind": "slanted-edge", "squares": [10, 7], "square_mm": 20.0})
    assert tone_shifts({0: first}, ["srgb"], {"board": squares}) == {0: 0.0}  # (no saddle corners)
