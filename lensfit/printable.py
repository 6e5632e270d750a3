"""Printable calibration targets: a ChArUco board laid out on a sheet of paper at its true size,
and the ``[[target]]`` entry of ``stack.toml`` that describes it.

The board is drawn by OpenCV (``CharucoBoard.generateImage``, the same drawing detection
expects) at a resolution where every marker cell is a whole number of pixels
(``lensfit.targets.charuco_texels_per_square``), then enlarged by a whole factor (nearest
neighbour, so the edges stay exact) to at least the requested dots per inch, and placed in the
middle of a white page. The file's resolution (PNG ``pHYs``, PDF page size) is set so that a
square prints at exactly ``square_mm`` when printed at 100 % ("actual size", no "fit to page").
Printers and drivers still scale a little: measure a printed square and, where it differs,
scale ``square_mm`` and ``marker_mm`` in the entry by the measured ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.errors import InputError

#: Paper sizes (width, height) in mm, portrait; landscape swaps them.
PAPER_MM = {"a4": (210.0, 297.0), "a3": (297.0, 420.0), "a2": (420.0, 594.0), "letter": (215.9, 279.4),
            "tabloid": (279.4, 431.8)}
#: White margin kept around the board (printers do not print to the edge), mm.
MARGIN_MM = 12.0
#: Marker side as a share of the square side (OpenCV's examples use 0.7-0.8).
MARKER_RATIO = 0.75


@dataclass(frozen=True)
class PrintableBoard:
    """A board on a page: ``image`` (uint8, height x width, the whole page), ``dpi`` (exact dots
    per inch of the file), ``page_mm`` (width, height) and ``entry`` (stack.toml's [[target]])."""

    image: np.ndarray
    dpi: float
    page_mm: tuple[float, float]
    entry: dict[str, Any]


def paper_size(name: str) -> tuple[float, float]:
    """(width, height) mm of a paper name (a4, a3, a2, letter, tabloid, with ``-landscape``) or
    ``WxH`` in mm (e.g. ``600x400``)."""
    text = name.strip().lower()
    landscape = text.endswith("-landscape")
    text = text.removesuffix("-landscape")
    if text in PAPER_MM:
        w, h = PAPER_MM[text]
    else:
        try:
            w, h = (float(v) for v in text.split("x"))
        except ValueError:
            raise InputError("paper", name, f"one of {', '.join(PAPER_MM)} (optionally -landscape) or WxH in mm, "
                             "e.g. 600x400") from None
        if not (50.0 <= w <= 5000.0 and 50.0 <= h <= 5000.0):
            raise InputError("paper", name, "a sheet from 50 to 5000 mm a side")
    return (h, w) if landscape else (w, h)


def charuco_page(paper: str = "a4-landscape", squares: tuple[int, int] = (9, 6), square_mm: float | None = None,
                 marker_mm: float | None = None, dictionary: str = "DICT_5X5_100", dpi: float = 300.0,
                 target_id: str = "board") -> PrintableBoard:
    """A ChArUco board on a page (see the module notes).

    ``square_mm`` defaults to the largest whole half-millimetre that fits ``squares`` inside the
    page's margins; ``marker_mm`` to ``MARKER_RATIO`` of it (a whole half-millimetre).
    """
    from lensfit.targets import aruco_dictionary, aruco_dictionary_names, charuco_board, charuco_texels_per_square

    page_w, page_h = paper_size(paper)
    cols, rows = (int(v) for v in squares)
    if not (3 <= cols <= 60 and 3 <= rows <= 60):
        raise InputError("squares", f"{cols} x {rows}", "3 to 60 squares each way")
    if dictionary not in aruco_dictionary_names():
        raise InputError("dictionary", dictionary, "an OpenCV ArUco dictionary, e.g. DICT_5X5_100 or DICT_4X4_50")
    room_w, room_h = page_w - 2 * MARGIN_MM, page_h - 2 * MARGIN_MM
    if square_mm is None:
        square_mm = math.floor(2.0 * min(room_w / cols, room_h / rows)) / 2.0
    if not (square_mm > 0 and math.isfinite(square_mm)):
        raise InputError("square_mm", square_mm, "> 0 mm")
    if cols * square_mm > room_w + 1e-9 or rows * square_mm > room_h + 1e-9:
        raise InputError("square_mm", square_mm, f"at most {min(room_w / cols, room_h / rows):.1f} mm for "
                         f"{cols} x {rows} squares on {paper} ({page_w:g} x {page_h:g} mm, {MARGIN_MM:g} mm margins)",
                         "or a larger paper / fewer squares")
    if marker_mm is None:
        marker_mm = math.floor(2.0 * MARKER_RATIO * square_mm) / 2.0
    if not (0 < marker_mm < square_mm):
        raise InputError("marker_mm", marker_mm, f"between 0 and the square side ({square_mm:g} mm)")
    n_markers = (cols * rows) // 2
    capacity = aruco_dictionary(dictionary).bytesList.shape[0]
    if n_markers > capacity:
        raise InputError("squares", f"{cols} x {rows}", f"at most {capacity} markers for {dictionary} "
                         f"({n_markers} needed)", "or a larger dictionary (e.g. DICT_5X5_250)")
    if not (72.0 <= dpi <= 2400.0):
        raise InputError("dpi", dpi, "72 to 2400 dots per inch")
    n = charuco_texels_per_square(square_mm, marker_mm, dictionary)
    scale = max(1, math.ceil(dpi * square_mm / 25.4 / n))
    px_per_square = n * scale
    exact_dpi = px_per_square * 25.4 / square_mm
    board = charuco_board((cols, rows), square_mm, marker_mm, dictionary)
    drawing = board.generateImage((cols * n, rows * n), marginSize=0, borderBits=1)
    drawing = np.repeat(np.repeat(drawing, scale, axis=0), scale, axis=1)
    width_px, height_px = round(page_w / 25.4 * exact_dpi), round(page_h / 25.4 * exact_dpi)
    page = np.full((height_px, width_px), 255, np.uint8)
    y0, x0 = (height_px - drawing.shape[0]) // 2, (width_px - drawing.shape[1]) // 2
    page[y0:y0 + drawing.shape[0], x0:x0 + drawing.shape[1]] = drawing
    entry = {"id": target_id, "kind": "charuco", "squares": [cols, rows], "square_mm": float(square_mm),
             "marker_mm": float(marker_mm), "dictionary": dictionary}
    return PrintableBoard(page, exact_dpi, (page_w, page_h), entry)


def target_toml(entry: dict[str, Any]) -> str:
    """The ``[[target]]`` table of stack.toml for a printed board."""
    import json

    lines = [f"{k} = {json.dumps(v)}" for k, v in entry.items()]  # JSON scalars and lists are TOML here
    return "[[target]]\n" + "\n".join(lines) + "\n"


def write_page(board: PrintableBoard, path: str | Path, program: str = "lensfit") -> None:
    """Write the page as PNG (with its dpi) or PDF (one page of the paper's size) by suffix."""
    from PIL import Image, PngImagePlugin

    from lensfit.outputs import software_tag

    path = Path(path)
    img = Image.fromarray(board.image, mode="L")
    if path.suffix.lower() == ".pdf":
        img.save(path, "PDF", resolution=board.dpi, creator=software_tag(program),
                 title=f"ChArUco {board.entry['squares'][0]}x{board.entry['squares'][1]}, "
                       f"{board.entry['square_mm']:g} mm squares")
    else:
        info = PngImagePlugin.PngInfo()
        info.add_text("Software", software_tag(program))
        img.save(path, "PNG", dpi=(board.dpi, board.dpi), pnginfo=info)
