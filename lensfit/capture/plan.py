"""Capture planning (``lensfit plan``): where to put the target, and how many shots, for a
requested accuracy of f, N and the focus distance -- what accuracy costs in capture.

For a lens guess (focal length f, f-number N, focus distance X from the lens), a sensor and a
printed board, the plan

1. finds the target distances a shot can use: the board fits in the frame (90 % of its width
   and height), its squares are large enough to detect (``min_square_px``) and the blur is
   small enough that edges have room (blur diameter at most ``max_blur_fraction`` of a square,
   and on a ChArUco board at most ``CLEAN_ROOM_SHARE`` of the clean room between a square's
   edge and its marker, both sides) and the markers still decode (at most ``MARKER_CELLS`` of
   a marker's cells);
2. spreads n fronto-parallel shots evenly in inverse distance over that range (both sides of
   focus where the range allows it: a V measured on one arm cannot tell N from X well);
3. computes the Cramer-Rao bound of the thin-lens circle-of-confusion fit for each n:
   per edge ``c = (f/N) S |1/d - 1/X| / p`` with the sensor distance ``1/S = 1/f - 1/X``,
   each edge measured with sigma ``sqrt(edge_sigma_px^2 + (edge_sigma_rel c)^2)``, every
   interior edge of the board once per shot, and the calibration's focal length in px
   (``S / p``) known to ``calibration_sigma_rel``, which scales the target distances the poses
   give with it, and so f, N and X alike;
4. returns the smallest n whose 95 % half-intervals (1.96 sigma) reach the goal for every
   quantity, and the whole cost curve.

It is a lower bound for a fronto-parallel, unbiased capture: the intervals the fit reports
also carry the calibration and the estimator's systematic terms, and calibration itself wants
some shots tilted by 20-40 degrees. Defaults of the edge noise follow the edge estimator's
figures of `lensfit bench-measure` (about 0.03-0.05 px on clean edges, a few per cent of the blur on noisy
ones); state your own with the arguments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lensfit.errors import InputError

QUANTITIES = ("focal_length_mm", "f_number", "focus_distance_mm")
#: The calibration's fewest views (some tilted by 20-40 degrees): the plan never asks for fewer.
MIN_SHOTS = 6
#: A ChArUco edge is measured in the white between the square's edge and its marker: the blur
#: diameter may fill this share of twice that gap (its radius, of the gap) before the window is
#: cut short (flag window_truncated).
CLEAN_ROOM_SHARE = 0.8
#: Markers decode under a blur diameter of up to about this many of their cells (bits + border):
#: rendered 4x4 markers through a 16 mm f/2 lens gave every corner at 0.6 cells, every one or
#: most at 0.85-0.88 (by the render's noise), 9-12 of 15 at 1.1-1.3 cells behind the focus and
#: none at 1.1 cells before it; 0.7 keeps a margin.
MARKER_CELLS = 0.7


@dataclass(frozen=True)
class Board:
    """What matters of a target for planning: its printed size, square side and interior edges."""

    width_mm: float
    height_mm: float
    square_mm: float
    edges: int
    #: a ChArUco board's marker side and its cells across (bits + 2 border); None: a checkerboard
    marker_mm: float | None = None
    marker_cells: int | None = None

    def max_blur(self, square_px: np.ndarray, max_blur_fraction: float) -> np.ndarray:
        """The largest blur diameter (px) an edge of this board measures at a square size in px."""
        limit = max_blur_fraction * square_px
        if self.marker_mm is not None:
            scale = square_px / self.square_mm  # px per mm on the board
            clean = 0.5 * (self.square_mm - self.marker_mm) * scale
            limit = np.minimum(limit, CLEAN_ROOM_SHARE * 2.0 * clean)
            limit = np.minimum(limit, MARKER_CELLS * self.marker_mm / self.marker_cells * scale)
        return limit

    @classmethod
    def from_entry(cls, entry: dict[str, Any]) -> "Board":
        """From a stack.toml ``[[target]]`` table (charuco or checkerboard)."""
        if entry.get("kind") not in ("charuco", "checkerboard"):
            raise InputError("target.kind", entry.get("kind"), "charuco or checkerboard for planning")
        cols, rows = (int(v) for v in entry["squares"])
        sq = float(entry["square_mm"])
        marker, cells = None, None
        if entry["kind"] == "charuco":
            from lensfit.calibration.targets import aruco_dictionary, aruco_dictionary_names

            marker = float(entry["marker_mm"])
            name = str(entry.get("dictionary", "DICT_4X4_50"))
            if name not in aruco_dictionary_names():
                raise InputError("target.dictionary", name, "one of OpenCV's ArUco dictionaries (DICT_4X4_50, ...)")
            cells = aruco_dictionary(name).markerSize + 2  # the marker's bits and its black border
        # edges between neighbouring interior corners
        return cls(cols * sq, rows * sq, sq, (cols - 2) * (rows - 1) + (cols - 1) * (rows - 2), marker, cells)


@dataclass
class Plan:
    """A capture plan: the usable distance range, the chosen shots and the cost curve."""

    usable_mm: tuple[float, float]
    shots: int | None
    distances_mm: list[float]
    sigma: dict[str, float]  # 1-sigma bound of each quantity (relative) for the chosen shots
    curve: list[dict[str, Any]]  # per n: relative 1-sigma bound of each quantity
    notes: list[str] = field(default_factory=list)
    goal_rel: float = 0.01

    def to_json_dict(self) -> dict[str, Any]:
        return {"usable_distance_mm": list(self.usable_mm), "shots": self.shots, "distances_mm": self.distances_mm,
                "relative_sigma": self.sigma, "goal_relative_ci95": self.goal_rel, "curve": self.curve,
                "notes": self.notes}


def _blur_px(f: float, N: float, x: float, w: np.ndarray, pitch: float) -> np.ndarray:
    S = 1.0 / (1.0 / f - x)
    return (f / N) * S * np.abs(w - x) / pitch


def bound(f: float, N: float, x: float, w_shots: np.ndarray, board: Board, pitch: float, *,
          edge_sigma_px: float, edge_sigma_rel: float, calibration_sigma_rel: float,
          distances_scale: bool = True) -> dict[str, float]:
    """Relative 1-sigma Cramer-Rao bounds on f, N, X for shots at inverse distances ``w_shots``
    (1/mm), ``board.edges`` edges each (see the module notes). inf where not determined.

    ``distances_scale``: the calibration's focal length in px and the target distances its poses
    give are one measurement: a relative error e in the first scales every distance by 1 + e,
    and with them the fitted f, N and X (the blur's slope A S / p |1/d - 1/X| keeps A). The
    bound is then the blur's own (the focal length in px exact) with ``calibration_sigma_rel``
    added in quadrature to each quantity. False: the distances held exact and the focal length
    in px a separate observation, as the fit's solver sees them (``lensfit.fitting.cramer_rao``)."""
    if distances_scale:
        blur_only = bound(f, N, x, w_shots, board, pitch, edge_sigma_px=edge_sigma_px, edge_sigma_rel=edge_sigma_rel,
                          calibration_sigma_rel=1e-7, distances_scale=False)
        return {q: math.hypot(v, calibration_sigma_rel) for q, v in blur_only.items()}
    theta = np.array([math.log(f), x * f, math.log(N)])  # x scaled by f: columns of similar size

    def model(t):
        ff, xx, nn = math.exp(t[0]), t[1] / math.exp(t[0]), math.exp(t[2])
        S = 1.0 / (1.0 / ff - xx)
        c = (ff / nn) * S * np.sqrt((w_shots - xx) ** 2 + (1e-9 / ff) ** 2) / pitch
        return np.concatenate([c, [S]])

    c0 = model(theta)
    sig = np.concatenate([np.sqrt(edge_sigma_px**2 + (edge_sigma_rel * c0[:-1]) ** 2) / math.sqrt(board.edges),
                          [calibration_sigma_rel * c0[-1]]])
    jac = np.empty((len(c0), 3))
    for j in range(3):
        h = 1e-6 * max(1.0, abs(theta[j]))
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        jac[:, j] = (model(tp) - model(tm)) / (2 * h)
    J = jac / sig[:, None]
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return {q: math.inf for q in QUANTITIES}
    var = np.diag(cov)
    if np.any(~np.isfinite(var)) or np.any(var < 0):
        return {q: math.inf for q in QUANTITIES}
    # X = 1/x: sigma_X / X = sigma_x / x; x = t1 / f: d x = (d t1 - t1 d log f) / f
    g = np.array([-theta[1], 1.0, 0.0]) / f
    var_x = float(g @ cov @ g)
    return {"focal_length_mm": float(math.sqrt(var[0])), "f_number": float(math.sqrt(var[2])),
            "focus_distance_mm": float(math.sqrt(max(var_x, 0.0)) / abs(x)) if x > 0 else math.inf}


def plan_capture(focal_length_mm: float, f_number: float, focus_distance_mm: float, *, pixel_pitch_mm: float,
                 width_px: int, height_px: int, board: Board, goal_rel: float = 0.01, max_shots: int = 48,
                 edge_sigma_px: float = 0.05, edge_sigma_rel: float = 0.02, calibration_sigma_rel: float = 0.001,
                 min_square_px: float = 24.0, max_blur_fraction: float = 0.25) -> Plan:
    """The smallest fronto-parallel capture reaching ``goal_rel`` (95 % half-interval, relative)
    on f, N and X (see the module notes).

    Raises
    ------
    InputError
        A lens or sensor out of range, or a board no distance can use.
    """
    f, N, X = float(focal_length_mm), float(f_number), float(focus_distance_mm)
    checks = [("focal_length_mm", f, f > 0 and math.isfinite(f), "> 0 mm"),
              ("f_number", N, 0.5 <= N <= 1000, "between 0.5 and 1000"),
              ("focus_distance_mm", X, X > f, "> the focal length (or inf)"),
              ("pixel_pitch_mm", pixel_pitch_mm, 1e-4 <= pixel_pitch_mm <= 1.0, "between 0.0001 and 1 mm"),
              ("goal", goal_rel, 0 < goal_rel < 1, "between 0 and 100 %"),
              ("max_shots", max_shots, MIN_SHOTS <= max_shots <= 1000, f"between {MIN_SHOTS} and 1000"),
              ("width_px", width_px, width_px >= 16 and height_px >= 16, "at least 16 x 16 px")]
    for name, value, ok, req in checks:
        if not ok:
            raise InputError(name, value, req)
    x = 0.0 if math.isinf(X) else 1.0 / X
    S = 1.0 / (1.0 / f - x)
    sensor_w, sensor_h = width_px * pixel_pitch_mm, height_px * pixel_pitch_mm
    # usable inverse distances on a fine grid from 100 m to 1.5 f
    w = np.linspace(1.0 / 100_000.0, 1.0 / (1.5 * f), 20001)
    mag = S * w  # image size / object size (paraxial, distance d = 1/w)
    fits = (board.width_mm * mag <= 0.9 * sensor_w) & (board.height_mm * mag <= 0.9 * sensor_h)
    square_px = board.square_mm * mag / pixel_pitch_mm
    blur = _blur_px(f, N, x, w, pixel_pitch_mm)
    ok = fits & (square_px >= min_square_px) & (blur <= board.max_blur(square_px, max_blur_fraction))
    if not ok.any():
        why = ("the board does not fit the frame where its squares are large enough to detect" if not (
            fits & (square_px >= min_square_px)).any() else "the blur swamps the squares at every distance that fits")
        raise InputError("target", f"{board.width_mm:g} x {board.height_mm:g} mm, {board.square_mm:g} mm squares",
                         "usable at some distance", f"{why}; use a board with more, smaller squares or a larger one, "
                         "or stop down")
    idx = np.flatnonzero(ok)
    # the contiguous run holding the most inverse-distance span
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    run = max(runs, key=lambda r: w[r[-1]] - w[r[0]])
    w_lo, w_hi = float(w[run[0]]), float(w[run[-1]])
    notes = []
    if not (w_lo < x < w_hi):
        side = "nearer than" if x <= w_lo else "farther than"
        notes.append(f"every usable distance is {side} the focus distance: the blur is measured on one side of focus "
                     "only, so N and the focus distance correlate; where you can, add a larger board for far shots "
                     "or a smaller one for near shots")
    curve, chosen = [], None
    for n in range(3, max_shots + 1):
        shots = np.linspace(w_lo, w_hi, n)
        b = bound(f, N, x, shots, board, pixel_pitch_mm, edge_sigma_px=edge_sigma_px, edge_sigma_rel=edge_sigma_rel,
                  calibration_sigma_rel=calibration_sigma_rel)
        curve.append({"shots": n, **b, "distances_mm": [float(1.0 / v) for v in shots[::-1]]})
        if chosen is None and all(1.96 * b[q] <= goal_rel for q in QUANTITIES if not (q == "focus_distance_mm"
                                                                                    and x == 0)):
            chosen = n
    if x == 0:
        notes.append("focus at infinity: the focus distance's relative error is undefined; its inverse is bounded")
    if chosen is not None and chosen < MIN_SHOTS:
        notes.append(f"{chosen} shots would reach the goal; the calibration wants at least {MIN_SHOTS} views, some "
                     f"tilted by 20-40 degrees: the plan takes {MIN_SHOTS}")
        chosen = MIN_SHOTS
    n_best = chosen if chosen is not None else max_shots
    shots = np.linspace(w_lo, w_hi, n_best)
    if chosen is None:
        last = curve[-1]
        limiting = max(QUANTITIES, key=lambda q: last[q] if math.isfinite(last[q]) else 1e300)
        notes.append(f"{max_shots} shots do not reach {100 * goal_rel:g} % on {limiting} "
                     f"(bound {100 * 1.96 * last[limiting]:.2g} %): the edge noise or the calibration limits it; "
                     "a larger aperture (more blur per distance) or a board usable over a wider range helps")
    return Plan((float(1.0 / w_hi), float(1.0 / w_lo)), chosen, [float(1.0 / v) for v in shots[::-1]],
                {q: curve[n_best - 3][q] for q in QUANTITIES}, curve, notes, goal_rel)


def blur_at(focal_length_mm: float, f_number: float, focus_distance_mm: float, distance_mm: float,
            pixel_pitch_mm: float) -> float:
    """Blur-disk diameter (px) of a thin lens at ``distance_mm`` (for the plan's table)."""
    x = 0.0 if math.isinf(focus_distance_mm) else 1.0 / focus_distance_mm
    return float(_blur_px(focal_length_mm, f_number, x, np.array([1.0 / distance_mm]), pixel_pitch_mm)[0])
