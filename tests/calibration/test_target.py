"""``lensfit target``: a printable ChArUco board at its true size, and its stack.toml entry.

Checked independently of the drawing code: OpenCV's detector finds every inner corner on the
written page (the PDF rasterised by PDFium, another program's reading of it), and their spacing,
converted with the file's own resolution, is the square side the entry states; the page is the
paper's size; the scale bar's cells measure 10 mm; each file records its [[target]] entry.
"""

from __future__ import annotations

import re
import tomllib
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from PIL import Image

from lensfit.cli import main
from lensfit.calibration.targets import Target


def test_png_board_detects_with_the_stated_geometry(tmp_path, capsys):
    out = tmp_path / "board.png"
    assert main(["target", "--out", str(out), "--paper", "a4-landscape", "--dpi", "150"]) == 0
    text = capsys.readouterr().out
    # the photographer's checklist comes with the page
    assert all(w in text for w in ("RAW", "stabilisation off", "autofocus off", "lens corrections", "tilted"))
    entry = dict(re.findall(r"^(\w+) = (.+)$", text, flags=re.M))
    square_mm = float(entry["square_mm"])
    cols, rows = (int(v) for v in re.findall(r"\d+", entry["squares"]))
    img = Image.open(out)
    dpi = img.info["dpi"][0]
    page = np.asarray(img, np.float64) / 255.0
    assert page.shape[1] / dpi * 25.4 == pytest.approx(297.0, abs=0.2)  # the page is A4 landscape
    spec = {"id": "board", "kind": "charuco", "squares": [cols, rows], "square_mm": square_mm,
            "marker_mm": float(entry["marker_mm"]), "dictionary": entry["dictionary"].strip('"')}
    det = Target(spec).detect(page)
    assert det is not None and len(det.ids) == (cols - 1) * (rows - 1)
    # Corner spacing in the file, at its resolution, is the square side in mm.
    order = np.argsort(det.ids)
    pts = det.image_points_px[order].reshape(rows - 1, cols - 1, 2)
    step_px = np.mean(np.hypot(*np.diff(pts, axis=1).reshape(-1, 2).T))
    assert step_px / dpi * 25.4 == pytest.approx(square_mm, rel=2e-3)
    assert cols * square_mm <= 297.0 - 24.0 and rows * square_mm <= 210.0 - 24.0


def _check_scale_bar(page, dpi, page_h_mm):
    """The 100 mm bar in the bottom margin, read along its middle row: 100 mm from its first dark
    pixel to the end of its last (white, outlined) cell, and its white cells centred 15, 35, ...
    95 mm from its start."""
    row = page[round((page_h_mm - 4.0 - 1.25) / 25.4 * dpi)] < 0.5
    change = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])))
    dark = [(a / dpi * 25.4, b / dpi * 25.4) for a, b in zip(change[::2], change[1::2])]
    x0 = dark[0][0]
    bar = [run for run in dark if run[0] < x0 + 100.5]
    assert bar[-1][1] - x0 == pytest.approx(100.0, abs=0.3)
    white = [(a[1] + b[0]) / 2 - x0 for a, b in zip(bar, bar[1:]) if b[0] - a[1] > 5.0]
    assert white == pytest.approx([15.0, 35.0, 55.0, 75.0, 95.0], abs=0.25)


def test_png_records_its_entry_and_carries_a_scale_bar(tmp_path):
    out = tmp_path / "board.png"
    assert main(["target", "--out", str(out), "--dpi", "200", "--id", "wall"]) == 0
    img = Image.open(out)
    record = tomllib.loads(img.info["Description"])["target"][0]
    assert record["id"] == "wall" and record["square_mm"] == 30.0 and record["dictionary"] == "DICT_5X5_100"
    _check_scale_bar(np.asarray(img, np.float64) / 255.0, img.info["dpi"][0], 210.0)


def test_pdf_is_vector_true_to_size_labelled_and_measurable(tmp_path):
    pdfium = pytest.importorskip("pypdfium2")
    out = tmp_path / "board.pdf"
    assert main(["target", "--out", str(out), "--id", "bench-left", "--squares", "8", "5"]) == 0
    pdf = pdfium.PdfDocument(str(out))
    record = tomllib.loads(pdf.get_metadata_dict()["Subject"])["target"][0]
    page = pdf[0]
    # no raster inside: the board is drawn as paths
    assert not list(page.get_objects(filter=[pdfium.raw.FPDF_PAGEOBJ_IMAGE]))
    assert list(page.get_objects(filter=[pdfium.raw.FPDF_PAGEOBJ_PATH]))
    w_pt, h_pt = page.get_size()
    assert (w_pt / 72 * 25.4, h_pt / 72 * 25.4) == pytest.approx((297.0, 210.0), abs=0.05)
    text = page.get_textpage().get_text_range()
    for word in ("bench-left", "8 x 5", f"{record['square_mm']:g} mm", "DICT_5X5_100", "100 %",
                 "--measured-square-mm"):
        assert word in text
    dpi = 200.0
    pixels = np.asarray(page.render(scale=dpi / 72, grayscale=True).to_pil(), np.float64) / 255.0
    det = Target(record).detect(pixels)
    assert det is not None and len(det.ids) == 7 * 4
    pts = det.image_points_px[np.argsort(det.ids)].reshape(4, 7, 2)
    step_px = np.mean(np.hypot(*np.diff(pts, axis=1).reshape(-1, 2).T))
    assert step_px / dpi * 25.4 == pytest.approx(record["square_mm"], rel=2e-3)
    _check_scale_bar(pixels, dpi, 210.0)


def test_svg_is_vector_at_the_paper_size_with_its_entry(tmp_path):
    out = tmp_path / "board.svg"
    assert main(["target", "--out", str(out), "--paper", "a3"]) == 0
    root = ET.parse(out).getroot()
    ns = {"svg": "http://www.w3.org/2000/svg", "dc": "http://purl.org/dc/elements/1.1/"}
    size_mm = [float(root.get(k).removesuffix("pt")) / 72 * 25.4 for k in ("width", "height")]
    assert size_mm == pytest.approx([297.0, 420.0], abs=0.05)
    assert root.find(".//svg:image", ns) is None
    record = tomllib.loads(root.find(".//dc:description", ns).text)["target"][0]
    assert record["squares"] == [9, 6] and record["kind"] == "charuco"


def test_pdf_page_is_the_paper_size(tmp_path, capsys):
    out = tmp_path / "board.pdf"
    assert main(["target", "--out", str(out), "--paper", "letter", "--dpi", "100"]) == 0
    box = re.search(rb"/MediaBox \[ *0 0 ([\d.]+) ([\d.]+) *\]", out.read_bytes())
    assert box is not None
    assert float(box.group(1)) / 72 * 25.4 == pytest.approx(215.9, abs=0.05)
    assert float(box.group(2)) / 72 * 25.4 == pytest.approx(279.4, abs=0.05)
    # A second run does not replace it silently; with --force it does (lensfit wrote it).
    assert main(["target", "--out", str(out), "--paper", "letter", "--dpi", "100"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["target", "--out", str(out), "--paper", "letter", "--dpi", "100", "--force"]) == 0


@pytest.mark.parametrize("args,says", [
    (["--square-mm", "50"], "--square-mm"),
    (["--squares", "30", "20"], "DICT_5X5_250"),
    (["--paper", "napkin"], "--paper"),
    (["--dictionary", "DICT_9X9_1"], "--dictionary"),
])
def test_impossible_boards_are_refused_naming_the_option(tmp_path, capsys, args, says):
    out = tmp_path / "board.png"
    assert main(["target", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def _copies_written_out(linear, white, gammas=(1.0, 2.2)):
    """The detectors' 8-bit copies as their definition says, on the whole image at once."""
    import cv2

    v = np.clip(linear / white, 0.0, 1.0)
    return [np.rint(v * 255.0).astype(np.uint8) if g == 1.0
            else cv2.convertScaleAbs(cv2.pow(v.astype(np.float32), 1 / g), alpha=255.0) for g in gammas]


def test_detection_copies_are_made_in_blocks_when_asked_with_the_same_values():
    """Copies made block by block, each when first asked for, equal the whole-image definition:
    exactly below SUBSAMPLED_WHITE_PX; above it the white point comes from every 4th pixel of
    every 4th row and moves a level at most."""
    from lensfit.calibration import targets

    rng = np.random.default_rng(0)
    small = rng.gamma(2.0, 0.2, (700, 900))
    copies = targets.detection_copies(small)
    assert len(copies._made) == 0
    first = copies[0]
    assert len(copies._made) == 1  # the gamma copy not made until asked for
    exact = _copies_written_out(small, float(np.percentile(small, 99.9)))
    assert np.array_equal(first, exact[0]) and np.array_equal(copies[1], exact[1])
    large = rng.gamma(2.0, 0.2, (1500, 3000))
    assert large.size > targets.SUBSAMPLED_WHITE_PX
    exact = _copies_written_out(large, float(np.percentile(large, 99.9)))
    for got, want in zip(targets.detection_copies(large), exact):
        diff = np.abs(got.astype(int) - want.astype(int))
        assert diff.max() <= 1 and (diff == 0).mean() > 0.9
