"""Printable calibration targets: a ChArUco board laid out on a sheet of paper at its true size,
and the ``[[target]]`` entry of ``stack.toml`` that describes it.

The board is drawn by OpenCV (``CharucoBoard.generateImage``, the same drawing detection
expects) at a resolution where every marker cell is a whole number of texels
(``lensfit.calibration.targets.charuco_texels_per_square``) and placed in the middle of a white page.

- PDF and SVG are vector pages (matplotlib): the drawing's dark texels become one filled path of
  rectangles in millimetres, so the board prints sharp at any printer resolution; the page is
  the paper's size.
- PNG is a raster: the drawing enlarged by a whole factor (nearest neighbour, so the edges stay
  exact) to at least the requested dots per inch, its resolution written in ``pHYs``.

Every page carries, in the margin, a label (the target's id, squares, square and marker sizes,
dictionary) and a 10 mm-chequered scale bar, and the files record the ``[[target]]`` entry
(PDF Subject, SVG description, PNG text). A square prints at exactly ``square_mm`` when printed
at 100 % ("actual size", no "fit to page"); printers and drivers still scale a little: measure a
printed square (or the scale bar) and give it to ``lensfit init --measured-square-mm``.
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


#: Scale bar: chequered in steps of this many mm, at most this long, this tall.
SCALE_STEP_MM, SCALE_MAX_MM, SCALE_HEIGHT_MM = 10.0, 100.0, 2.5
#: The outline of the scale bar's white cells, mm.
SCALE_LINE_MM = 0.2
#: Label text height (cap height), mm, and the gap between the sheet's edge and label or bar.
LABEL_MM, EDGE_GAP_MM = 2.5, 4.0


@dataclass(frozen=True)
class PrintableBoard:
    """A board on a page: ``image`` (uint8, height x width, the whole page at ``dpi``, label and
    scale bar included), ``dpi`` (exact dots per inch of the raster), ``page_mm`` (width,
    height), ``entry`` (stack.toml's [[target]]), ``drawing`` (OpenCV's board at whole texels,
    0 dark, 255 light) and ``board_origin_mm`` (the board's top-left corner on the page)."""

    image: np.ndarray
    dpi: float
    page_mm: tuple[float, float]
    entry: dict[str, Any]
    drawing: np.ndarray
    board_origin_mm: tuple[float, float]

    @property
    def label(self) -> str:
        """The line printed in the top margin: what board this is."""
        e = self.entry
        return (f"lensfit target '{e['id']}': ChArUco {e['squares'][0]} x {e['squares'][1]} squares of "
                f"{e['square_mm']:g} mm, markers {e['marker_mm']:g} mm, {e['dictionary']}")

    @property
    def instruction(self) -> str:
        """The line printed beside the scale bar: how to check the print."""
        return (f"{self.scale_bar_mm:g} mm. Print at 100 % (actual size). A square not "
                f"{self.entry['square_mm']:g} mm? lensfit init --measured-square-mm")

    def texts(self) -> list[tuple[str, float, float, float]]:
        """(text, x, baseline y, room to the right) mm of the label and the instruction."""
        x0, (page_w, page_h) = self.board_origin_mm[0], self.page_mm
        x1 = x0 + self.scale_bar_mm + 3.0
        return [(self.label, x0, EDGE_GAP_MM + LABEL_MM, page_w - EDGE_GAP_MM - x0),
                (self.instruction, x1, page_h - EDGE_GAP_MM, page_w - EDGE_GAP_MM - x1)]

    @property
    def scale_bar_mm(self) -> float:
        """Length of the scale bar: whole steps, at most SCALE_MAX_MM and half the board's width
        (the rest of the line holds the instruction)."""
        width = self.entry["squares"][0] * self.entry["square_mm"] / 2
        return max(SCALE_STEP_MM, min(SCALE_MAX_MM, SCALE_STEP_MM * math.floor(width / SCALE_STEP_MM)))

    def scale_bar(self) -> list[tuple[float, float, float, float, bool]]:
        """The scale bar's cells (x, y, width, height mm from the page's top-left, dark?): a row
        of SCALE_STEP_MM cells, alternately dark and outlined, in the bottom margin."""
        x0 = self.board_origin_mm[0]
        y0 = self.page_mm[1] - EDGE_GAP_MM - SCALE_HEIGHT_MM
        n = round(self.scale_bar_mm / SCALE_STEP_MM)
        return [(x0 + k * SCALE_STEP_MM, y0, SCALE_STEP_MM, SCALE_HEIGHT_MM, k % 2 == 0) for k in range(n)]


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
    from lensfit.calibration.targets import (aruco_dictionary, aruco_dictionary_names, charuco_board,
                                             charuco_texels_per_square)

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
    texels = board.generateImage((cols * n, rows * n), marginSize=0, borderBits=1)
    drawing = np.repeat(np.repeat(texels, scale, axis=0), scale, axis=1)
    width_px, height_px = round(page_w / 25.4 * exact_dpi), round(page_h / 25.4 * exact_dpi)
    page = np.full((height_px, width_px), 255, np.uint8)
    y0, x0 = (height_px - drawing.shape[0]) // 2, (width_px - drawing.shape[1]) // 2
    page[y0:y0 + drawing.shape[0], x0:x0 + drawing.shape[1]] = drawing
    entry = {"id": target_id, "kind": "charuco", "squares": [cols, rows], "square_mm": float(square_mm),
             "marker_mm": float(marker_mm), "dictionary": dictionary}
    printable = PrintableBoard(page, exact_dpi, (page_w, page_h), entry, texels,
                               (x0 * 25.4 / exact_dpi, y0 * 25.4 / exact_dpi))
    _mark_raster(printable)
    return printable


def _mark_raster(board: PrintableBoard) -> None:
    """Draw the label and the scale bar into the raster page (in place)."""
    import cv2

    px = board.dpi / 25.4
    line_px = max(1, round(SCALE_LINE_MM * px))
    for x, y, w, h, dark in board.scale_bar():  # white cells outlined inside their own width
        p0, p1 = (round(x * px), round(y * px)), (round((x + w) * px) - 1, round((y + h) * px) - 1)
        cv2.rectangle(board.image, p0, p1, 0, -1)
        if not dark:
            cv2.rectangle(board.image, (p0[0] + line_px, p0[1] + line_px), (p1[0] - line_px, p1[1] - line_px), 255, -1)
    font = cv2.FONT_HERSHEY_SIMPLEX
    (_, cap_px), _ = cv2.getTextSize("H", font, 1.0, 1)
    size = LABEL_MM * px / cap_px
    thick = max(1, round(0.25 * px))
    for text, x, y, room_mm in board.texts():
        (w_px, _), _ = cv2.getTextSize(text, font, size, thick)
        fit = min(size, size * room_mm * px / max(w_px, 1))
        cv2.putText(board.image, text, (round(x * px), round(y * px)), font, fit, 0, thick, cv2.LINE_AA)


def _dark_rectangles(drawing: np.ndarray) -> list[tuple[int, int, int, int]]:
    """The dark texels of ``drawing`` as rectangles (column, row, width, height in texels): runs
    of each row, joined down the rows while the same run continues."""
    dark = drawing < 128
    rects, open_runs = [], {}
    for r in range(dark.shape[0] + 1):
        runs = set()
        if r < dark.shape[0]:
            change = np.flatnonzero(np.diff(np.concatenate([[0], dark[r].astype(np.int8), [0]])))
            runs = set(zip(change[::2].tolist(), change[1::2].tolist()))
        for run in [run for run in open_runs if run not in runs]:
            start = open_runs.pop(run)
            rects.append((run[0], start, run[1] - run[0], r - start))
        for run in runs:
            open_runs.setdefault(run, r)
    return rects


def page_figure(board: PrintableBoard):
    """The page as a matplotlib Figure of the paper's size, drawn in millimetres: the board as one
    filled path, the label and the scale bar (for the vector PDF and SVG)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import PathPatch, Rectangle
    from matplotlib.path import Path as MplPath

    page_w, page_h = board.page_mm
    fig = Figure(figsize=(page_w / 25.4, page_h / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, page_w)
    ax.set_ylim(page_h, 0.0)
    ax.set_axis_off()
    texel_mm = board.entry["square_mm"] * board.entry["squares"][0] / board.drawing.shape[1]
    x0, y0 = (page_w - board.drawing.shape[1] * texel_mm) / 2, (page_h - board.drawing.shape[0] * texel_mm) / 2
    verts, codes = [], []
    for c, r, w, h in _dark_rectangles(board.drawing):
        x, y = x0 + c * texel_mm, y0 + r * texel_mm
        verts += [(x, y), (x + w * texel_mm, y), (x + w * texel_mm, y + h * texel_mm), (x, y + h * texel_mm), (x, y)]
        codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
    ax.add_patch(PathPatch(MplPath(verts, codes), facecolor="black", edgecolor="none", linewidth=0))
    for x, y, w, h, dark in board.scale_bar():  # white cells outlined inside their own width
        ax.add_patch(Rectangle((x, y), w, h, facecolor="black", edgecolor="none", linewidth=0))
        if not dark:
            ax.add_patch(Rectangle((x + SCALE_LINE_MM, y + SCALE_LINE_MM), w - 2 * SCALE_LINE_MM,
                                   h - 2 * SCALE_LINE_MM, facecolor="white", edgecolor="none", linewidth=0))
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    points = LABEL_MM / 0.72 * 72 / 25.4  # a cap height of about 0.72 em
    for text, x, y, room_mm in board.texts():
        artist = ax.text(x, y, text, fontsize=points, va="baseline", ha="left")
        width_mm = artist.get_window_extent(renderer).width / fig.dpi * 25.4
        if width_mm > room_mm:  # a small sheet: the line shrinks to fit
            artist.set_fontsize(points * room_mm / width_mm)
    return fig


def target_toml(entry: dict[str, Any]) -> str:
    """The ``[[target]]`` table of stack.toml for a printed board."""
    import json

    lines = [f"{k} = {json.dumps(v)}" for k, v in entry.items()]  # JSON scalars and lists are TOML here
    return "[[target]]\n" + "\n".join(lines) + "\n"


#: The page formats ``write_page`` writes, by suffix.
PAGE_SUFFIXES = (".pdf", ".svg", ".png")


def write_page(board: PrintableBoard, path: str | Path, program: str = "lensfit") -> None:
    """Write the page by suffix: PDF or SVG (vector, the paper's size) or PNG (the raster at its
    dpi), each recording the entry."""
    from lensfit.outputs.writers import software_tag

    path = Path(path)
    kind = path.suffix.lower()
    title = (f"ChArUco {board.entry['squares'][0]} x {board.entry['squares'][1]}, "
             f"{board.entry['square_mm']:g} mm squares")
    record = target_toml(board.entry)
    if kind in (".pdf", ".svg"):
        from lensfit.outputs.plots import save_page

        save_page(page_figure(board), path, title=title, description=record, program=program)
    else:
        from PIL import Image, PngImagePlugin

        info = PngImagePlugin.PngInfo()
        info.add_text("Software", software_tag(program))
        info.add_text("Description", record)
        Image.fromarray(board.image, mode="L").save(path, "PNG", dpi=(board.dpi, board.dpi), pnginfo=info)
