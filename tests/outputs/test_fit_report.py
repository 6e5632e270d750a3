"""The HTML fit report: one page with the estimates, the fit plot and per image the detected
corners and measured edges coloured by blur and residual; a bad image stands out."""

from __future__ import annotations

import copy
import dataclasses
import re

import numpy as np
import pytest

from helpers import CHROMIUM, read_in_browser
from lensfit.cli import main as lensfit_main
from lensfit.outputs.report import edge_values, image_rows, write_fit_report
from lensfit.fitting import fit, results_document
from lensfit.outputs.writers import written_by
from lensfit.io.stack import load_stack


def test_an_image_whose_blur_is_wrong_stands_out(calibration_samples):
    table = copy.deepcopy(calibration_samples)
    names = list(dict.fromkeys(s.image for s in table.samples))
    bad = names[3]
    # the image's edges read 40 % more blur than the lens gives (e.g. camera shake in that shot)
    table.samples = [dataclasses.replace(s, coc_diameter_px=s.coc_diameter_px * 1.4)
                     if s.image == bad and s.coc_diameter_px is not None else s for s in table.samples]
    result = fit(table)
    rows = {r["image"]: r for r in image_rows(table, *edge_values(table, result))}
    worst = max(rows.values(), key=lambda r: r["rms_residual_sigma"])
    assert worst["image"] == bad
    assert worst["rms_residual_sigma"] > 2 * np.median([r["rms_residual_sigma"] for r in rows.values()])
    # every sample of the table appears exactly once in the rows
    assert sum(r["edges"] for r in rows.values()) == len(table.samples)
    assert sum(r["used"] for r in rows.values()) == result.n_samples


def test_report_has_every_image_with_its_corners_and_edges(calibration_stack, calibration_samples, tmp_path):
    stack = load_stack(calibration_stack)
    result = fit(calibration_samples)
    document = results_document(result, ["lensfit", "fit", "stack"], None, intrinsics=calibration_samples.intrinsics)
    out = tmp_path / "report.html"
    write_fit_report(out, result, document, calibration_samples, stack)
    text = out.read_text()
    assert written_by(out) == "lensfit"
    # what decides trust: the calibration, the error budget, the command; one count of down-weighted
    # edges, the one the table and the plots use
    k = calibration_samples.intrinsics["a"]
    assert f"calibration: focal length {k.focal_length_px:.1f}" in text and "variance from: " in text
    assert "command: <code>lensfit fit stack</code>" in text
    down = int(np.sum(result.weights < 0.5))
    assert f"{down} down-weighted (robust weight below 0.5)" in text
    shown = re.findall(r"<h3 id='([^']+)'", text)
    assert shown == [im.file.name for im in stack.images if im.file.name in calibration_samples.corners_px
                     and any(s.image == im.file.name for s in calibration_samples.samples)]
    # overlays + the fit plot + where the boards were
    assert len(re.findall(r"data:image/png;base64,", text)) == len(shown) + 2
    # the corners kept for the overlays are the detections: inside the image, one set per image
    h, w = stack.shape
    for name, dets in calibration_samples.corners_px.items():
        for _, pts in dets:
            assert np.all((pts >= 0) & (pts < [w, h]))
    # and the samples' edges run between detected corners (within 2 px)
    for s in calibration_samples.samples[:40]:
        pts = np.concatenate([p for _, p in calibration_samples.corners_px[s.image]])
        for end in (s.start_px, s.end_px):
            assert np.min(np.hypot(*(pts - np.array(end)).T)) < 2.0


@pytest.mark.slow
def test_cli_report_written_once_replaced_only_with_force(calibration_stack, tmp_path, capsys):
    report = tmp_path / "r.html"
    assert lensfit_main(["fit", str(calibration_stack), "--report", str(report)]) == 0
    assert "<h1>" in report.read_text()
    assert lensfit_main(["fit", str(calibration_stack), "--report", str(report)]) == 2
    assert "--force" in capsys.readouterr().err
    mine = tmp_path / "mine.html"
    mine.write_text("<html>my notes</html>")
    assert lensfit_main(["fit", str(calibration_stack), "--report", str(mine), "--force"]) == 2
    assert mine.read_text() == "<html>my notes</html>"
    assert lensfit_main(["fit", str(calibration_stack), "--report", str(tmp_path / "r.txt")]) == 2


@pytest.mark.parametrize("value, sigma, shown", [(49.9356, 1.85, "49.9"), (1004.6, 5.02, "1004.6"),
                                                 (25.00536, 0.0088, "25.0054"), (None, 1.0, "inf"),
                                                 (3.1, 0.0, "3.1")])
def test_estimates_carry_the_digits_their_sigma_allows(value, sigma, shown):
    """Two significant digits of the sigma decide the estimate's last digit (the report printed
    six whatever the sigma); an unbounded interval end reads inf."""
    from lensfit.outputs.report import to_sigma

    assert to_sigma(value, sigma, "inf") == shown


@pytest.mark.skipif(CHROMIUM is None, reason="needs headless Chromium (Debian's package chromium; .ci/run installs it)")
def test_report_reads_right_in_a_browser_at_800_px(calibration_stack, calibration_samples, tmp_path):
    """The report rendered by headless Chromium in an 800 px wide window and read back from the
    browser's own layout: nothing wider than the window (tables scroll inside their box), every
    picture decodes, one count of down-weighted edges in the header and the table, and per image
    the corners' reprojection RMS and the board-pose view are there."""
    stack = load_stack(calibration_stack)
    result = fit(calibration_samples)
    document = results_document(result, ["lensfit", "fit", "stack"], None, intrinsics=calibration_samples.intrinsics)
    write_fit_report(tmp_path / "report.html", result, document, calibration_samples, stack)
    probe = read_in_browser(tmp_path / "report.html", tmp_path)
    assert probe["scroll"] <= probe["client"] <= 800 and probe["wide"] == 0
    assert probe["broken"] == 0 and probe["images"] >= 3
    images = next(t for t in probe["tables"] if "reprojection RMS (px)" in t[0])
    head = images[0]
    rows = {r[0]: dict(zip(head, r)) for r in images[1:]}
    assert set(rows) == {im.file.name for im in stack.images}
    down = int(np.sum(result.weights < 0.5))
    assert f"{down} down-weighted" in probe["header"]
    assert sum(int(r["down-weighted"]) for r in rows.values()) == down
    poses = calibration_samples.poses
    for name, r in rows.items():
        rms = [p.rms_px for (image, _), p in poses.items() if image == name]
        if rms:
            assert float(r["reprojection RMS (px)"]) == pytest.approx(max(rms), rel=0.05)
        else:  # no pose: no edges either, and the row says why
            assert r["reprojection RMS (px)"] == "" and r["edges"] == "0" and r["not measured: why"]
        assert int(r["corners"]) == sum(len(pts) for _, pts in calibration_samples.corners_px[name])
    assert "Where the boards were" in probe["text"] and "command: lensfit fit stack" in probe["text"]
    # what was assumed rather than measured, from the stack's [lens] (synth declares its thin lens)
    assert "assumptions: focusing unit; pupil magnification" in probe["text"]
