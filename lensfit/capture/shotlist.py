"""The capture plan as a one-page shot list to take to the shoot (``lensfit plan --shot-list``):
the lens guess and the board, each planned shot with its distance, how to turn the board and a
box to tick, the accuracy the plan promises, and the photographer's checklist. A4 portrait,
vector PDF or SVG (or PNG) by suffix, drawn by matplotlib."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

#: What a photographer must do for every shot of a setting (printed by ``lensfit target`` and on
#: the shot list).
CHECKLIST = ("RAW (or RAW + JPEG)", "a tripod; image stabilisation off",
             "focus set once per setting, then autofocus off between shots",
             "in-camera lens corrections (distortion, vignetting) off",
             "the same f-number and zoom for every shot of a setting",
             "white squares bright but not clipped")

#: How to turn the board, shot after shot: some views tilted by 20-40 degrees pin the
#: calibration's focal length (the same turns the plan's end-to-end test renders).
TURNS = ("face on", "top edge 25 deg away", "left edge 25 deg away", "top 20 deg towards, right 15 deg away",
         "right edge 25 deg away", "top 20 deg away, left 20 deg towards")

PAGE_MM = (210.0, 297.0)
#: Characters a line of 9 pt text holds between the page's 15 mm margins.
LINE_CHARS = 95


def shot_rows(distances_mm: list[float], blur_px: list[float]) -> list[tuple[int, float, float, str]]:
    """(shot number, distance mm, blur px, how to turn the board) for each planned shot."""
    return [(k + 1, d, b, TURNS[k % len(TURNS)]) for k, (d, b) in enumerate(zip(distances_mm, blur_px))]


def shot_list_figure(title: str, lines: list[str], rows: list[tuple[int, float, float, str]], promise: str):
    """The page (see the module notes) as a matplotlib Figure, drawn in millimetres from the top left."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    w, h = PAGE_MM
    fig = Figure(figsize=(w / 25.4, h / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, w)
    ax.set_ylim(h, 0.0)
    ax.set_axis_off()
    y = 20.0
    ax.text(15.0, y, title, fontsize=14, weight="bold", va="baseline")
    y += 8.0
    for line in (part for text in lines for part in textwrap.wrap(text, LINE_CHARS)):
        ax.text(15.0, y, line, fontsize=9, va="baseline")
        y += 5.0
    y += 4.0
    cols = (15.0, 30.0, 62.0, 88.0, 178.0)
    for x, name in zip(cols, ("shot", "distance (mm)", "blur (px)", "board", "taken")):
        ax.text(x, y, name, fontsize=9, weight="bold", va="baseline")
    y += 2.0
    ax.plot([15.0, 195.0], [y, y], color="black", lw=0.6)
    step = min(7.0, (h - 95.0 - y) / max(len(rows), 1))
    for number, distance, blur, turn in rows:
        y += step
        size = min(9.0, 0.6 * step / 0.3528)  # a row's text at most 60 % of its height (1 pt = 0.3528 mm)
        for x, text in zip(cols, (str(number), f"{distance:.0f}", f"{blur:.2f}", turn)):
            ax.text(x, y, text, fontsize=size, va="baseline")
        box = min(4.0, 0.8 * step)
        ax.add_patch(Rectangle((cols[-1] + 2.0, y - box + 0.5), box, box, fill=False, lw=0.6))
    y += 5.0
    for line in textwrap.wrap(promise, LINE_CHARS):
        y += 5.0
        ax.text(15.0, y, line, fontsize=9, va="baseline")
    y += 10.0
    ax.text(15.0, y, "For every shot of a setting:", fontsize=10, weight="bold", va="baseline")
    for item in CHECKLIST + ("the board flat, inside the frame, at the distance listed from the lens (within a few "
                             "per cent: the fit measures each one)",):
        for k, line in enumerate(textwrap.wrap(item, LINE_CHARS - 4)):
            y += 5.5 if k == 0 else 4.5
            ax.text(18.0 if k == 0 else 21.0, y, ("- " if k == 0 else "") + line, fontsize=9, va="baseline")
    return fig


def write_shot_list(path: str | Path, title: str, lines: list[str], rows, promise: str) -> None:
    """Write the page by suffix (.pdf, .svg, .png)."""
    from lensfit.outputs.plots import save_page

    save_page(shot_list_figure(title, lines, rows, promise), path, title=title,
              dpi=150 if Path(path).suffix.lower() == ".png" else None)


def promise_text(sigma: dict[str, float], goal_pct: float, reached: bool) -> str:
    """The accuracy line: each quantity's predicted 95 % half-interval."""
    parts = [f"{q.replace('_mm', '').replace('_', ' ')} {100 * 1.96 * v:.2g} %" for q, v in sigma.items()
             if math.isfinite(v)]
    head = "Predicted 95 % half-intervals" + ("" if reached else f" (the goal of {goal_pct:g} % is not reached)")
    return head + ": " + ", ".join(parts) + "."
