"""Calibration targets: their printed geometry, detection in images, and their straight edges.

Board frame (OpenCV's): origin at the pattern's top-left corner, x along the columns, y down
the rows, z = 0 on the board; mm. Detection works on 8-bit copies of the linear image (what
OpenCV's detectors take); measurement later uses the linear image itself, and the detected
corners are refined from the measured edge lines (``lensfit.measurement.edge_geometry.refine_corners``).

Kinds (``stack.toml`` ``[[target]] kind``):

- ``charuco``: OpenCV >= 4.7 ``CharucoDetector``; ``legacy_pattern = true`` for boards made
  before OpenCV 4.6 with an even number of rows.
- ``checkerboard``: ``cv2.findChessboardCornersSB`` on the inner corners.
- ``slanted-edge``: a dark square (side ``edge_mm``) on a light ground, found as the largest
  dark convex quadrilateral.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def aruco_dictionary_names() -> list[str]:
    """The predefined ArUco dictionaries OpenCV has (``DICT_4X4_50``, ...), sorted."""
    import cv2

    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int))


def aruco_dictionary(name: str):
    """OpenCV's predefined ArUco dictionary ``name`` (one of :func:`aruco_dictionary_names`): its
    ``markerSize`` (bits across) and ``bytesList`` (one row per marker)."""
    import cv2

    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def charuco_board(squares, square_mm: float, marker_mm: float, dictionary: str, legacy_pattern: bool = False):
    """OpenCV's ``CharucoBoard`` (OpenCV >= 4.7 API); ``legacy_pattern`` for boards made
    before OpenCV 4.6 with an even number of rows."""
    import cv2

    board = cv2.aruco.CharucoBoard(tuple(squares), float(square_mm), float(marker_mm), aruco_dictionary(dictionary))
    if legacy_pattern:
        board.setLegacyPattern(True)
    return board


def charuco_texels_per_square(square_mm: float, marker_mm: float, dictionary: str, minimum: int = 48) -> int:
    """Raster resolution (texels per square) at which OpenCV's ChArUco drawing is exact.

    The marker must span a whole number of texels, each of its (bits + 2) cells too, and the
    white border around it as well; otherwise ``generateImage`` resamples the marker and every
    bit edge moves by up to a texel. Returns the smallest such resolution >= ``minimum`` (or the
    closest one up to 512).
    """
    cells = aruco_dictionary(dictionary).markerSize + 2
    ratio = marker_mm / square_mm
    best, best_err = minimum, float("inf")
    for n in range(minimum, 513):
        marker = n * ratio
        err = abs(marker / cells - round(marker / cells)) * cells + abs((n - marker) / 2 - round((n - marker) / 2))
        if err < 1e-6:
            return n
        if err < best_err:
            best, best_err = n, err
    return best


@dataclass(frozen=True)
class Detection:
    """Corresponding points of one target in one image. ``point_cov_px2``: where known, the
    covariance of the image points' errors, (2N, 2N) in the order x0, y0, x1, ... (corners refined
    from edge lines share the lines' errors; :func:`lensfit.measurement.edge_geometry.refine_corners`)."""

    target_id: str
    object_points_mm: np.ndarray  # (N, 3) board frame
    image_points_px: np.ndarray  # (N, 2)
    ids: np.ndarray  # (N,) corner ids (board-specific numbering)
    point_cov_px2: np.ndarray | None = None


@dataclass(frozen=True)
class EdgeSegment:
    """A straight dark/light boundary on a target, with the clean room on each side.

    ``clear_left_mm``/``clear_right_mm``: distance from the edge, on each side (left = the side
    of the normal (-dy, dx) of start->end), over which the target is uniform.
    ``border_left_mm``/``border_right_mm``: beyond that clean room, a dark band this wide before
    the target's pattern goes on (a ChArUco marker's black border; 0 where nothing is known).
    """

    id: str
    start_mm: tuple[float, float]
    end_mm: tuple[float, float]
    clear_left_mm: float
    clear_right_mm: float
    corner_ids: tuple[int, int] = (-1, -1)
    border_left_mm: float = 0.0
    border_right_mm: float = 0.0


#: The gammas of the detectors' 8-bit copies (linear, and encoded as a display would).
DETECTION_GAMMAS = (1.0, 2.2)


def display_8bit(linear: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    """Linear image -> 8-bit copy for the detectors (scaled to its 99.9th percentile)."""
    return detection_copies(linear, (gamma,))[0]


#: Above this many pixels the copies' white point (the 99.9th percentile) is taken from every
#: 4th pixel of every 4th row: on a 24 MP image the full percentile took 0.8 s of the 1.9 s the
#: copies cost, and a million pixels place it within a level of the 8-bit copy. Smaller images
#: keep the exact percentile.
SUBSAMPLED_WHITE_PX = 4_000_000
#: Rows per block in which the copies are made.
COPY_BLOCK_ROWS = 256


class DetectionCopies(Sequence):
    """The 8-bit copies of a linear image that the detectors look at, one per gamma (scaled to
    its 99.9th percentile), each made when a detector first asks for it: most targets are found
    whole in the first (linear) copy, and the second is then never made (0.4 s of a 24 MP
    image). Made once per image and shared by every target in it."""

    def __init__(self, linear: np.ndarray, gammas: tuple[float, ...] = DETECTION_GAMMAS):
        self._linear, self._gammas = linear, tuple(gammas)
        self._made: dict[int, np.ndarray] = {}
        sample = linear[::4, ::4] if linear.size > SUBSAMPLED_WHITE_PX else linear
        self._white = max(float(np.percentile(sample, 99.9)), 1e-12)

    def __len__(self) -> int:
        return len(self._gammas)

    def __getitem__(self, k: int) -> np.ndarray:
        if not 0 <= k < len(self):
            raise IndexError(k)
        if k not in self._made:
            self._made[k] = self._copy(self._gammas[k])
        return self._made[k]

    def _copy(self, gamma: float) -> np.ndarray:
        """One copy, made in blocks of rows (each operation in place on a block: on a 24 MP image
        the whole-image temporaries took 2.2 s against 0.3 s, the values the same)."""
        import cv2

        out = np.empty(self._linear.shape, np.uint8)
        for r in range(0, self._linear.shape[0], COPY_BLOCK_ROWS):
            v = np.divide(self._linear[r:r + COPY_BLOCK_ROWS], self._white)
            np.clip(v, 0.0, 1.0, out=v)
            if gamma == 1.0:
                # The linear copy rounded in float64 (OpenCV's float working type there moved a few
                # levels of a noisy image, and with them the detected corners).
                np.multiply(v, 255.0, out=v)
                np.rint(v, out=v)
                out[r:r + COPY_BLOCK_ROWS] = v
            else:
                # The power in float32 (OpenCV's vectorised pow: a tenth of numpy's float64 time;
                # the copy is 8-bit, so float32 changes a level at most where it falls on a half),
                # scaled and rounded by OpenCV in float32 too (half to even, as numpy's).
                out[r:r + COPY_BLOCK_ROWS] = cv2.convertScaleAbs(cv2.pow(v.astype(np.float32), 1 / gamma), alpha=255.0)
        return out


def detection_copies(linear: np.ndarray, gammas: tuple[float, ...] = DETECTION_GAMMAS) -> DetectionCopies:
    """The 8-bit copies of a linear image that the detectors look at (:class:`DetectionCopies`)."""
    return DetectionCopies(linear, gammas)


@dataclass
class Target:
    """A target as the manifest describes it."""

    spec: dict[str, Any]
    _board: Any = field(default=None, repr=False)
    _texture: Any = field(default=None, repr=False)

    @property
    def id(self) -> str:
        return self.spec["id"]

    @property
    def kind(self) -> str:
        return self.spec["kind"]

    def charuco_board(self):
        if self._board is None:
            s = self.spec
            self._board = charuco_board(s["squares"], s["square_mm"], s["marker_mm"], s["dictionary"],
                                        bool(s.get("legacy_pattern", False)))
        return self._board

    # ------------------------------------------------------------------ geometry

    def square_is_dark(self) -> np.ndarray:
        """(rows, cols) boolean: which squares of a board are dark."""
        nx, ny = self.spec["squares"]
        if self.kind == "checkerboard":
            return (np.add.outer(np.arange(ny), np.arange(nx)) % 2) == 0
        n = 32
        img = self.charuco_board().generateImage((nx * n, ny * n), marginSize=0, borderBits=1)
        return img[2::n, 2::n][:ny, :nx] < 128  # a square's own colour shows in its corner

    def texture(self) -> tuple[np.ndarray, float]:
        """A board's printed pattern as (raster, mm per texel): 1 light, 0 dark; origin at the
        pattern's top-left corner. ChArUco rasters have whole-texel marker cells, so the raster
        is exact (``charuco_texels_per_square``)."""
        if self._texture is None:
            s = self.spec
            if self.kind == "charuco":
                n = charuco_texels_per_square(s["square_mm"], s["marker_mm"], s["dictionary"])
                nx, ny = s["squares"]
                img = self.charuco_board().generateImage((nx * n, ny * n), marginSize=0, borderBits=1)
                self._texture = ((img > 127).astype(np.float64), float(s["square_mm"]) / n)
            else:
                self._texture = ((~self.square_is_dark()).astype(np.float64), float(s["square_mm"]))
        return self._texture

    def inner_corners_mm(self) -> np.ndarray:
        """(rows-1)*(cols-1) inner corners, row-major (the ids of OpenCV's ChArUco corners)."""
        nx, ny = self.spec["squares"]
        sq = float(self.spec["square_mm"])
        jj, ii = np.mgrid[1:ny, 1:nx]
        return np.stack([ii.ravel() * sq, jj.ravel() * sq, np.zeros(ii.size)], axis=1)

    def edges(self) -> list[EdgeSegment]:
        """Straight edges between adjacent inner corners (boards) or the square's sides."""
        out: list[EdgeSegment] = []
        if self.kind in ("charuco", "checkerboard"):
            nx, ny = self.spec["squares"]
            sq = float(self.spec["square_mm"])
            dark = self.square_is_dark()
            # Light squares of a ChArUco board hold a marker: clear room is the white border.
            light_clear = sq if self.kind == "checkerboard" else 0.5 * (sq - float(self.spec["marker_mm"]))
            # ... and beyond it the marker's black border, one of its cells (bits across and a
            # border cell on either side).
            light_border = 0.0 if self.kind == "checkerboard" else float(self.spec["marker_mm"]) / (
                aruco_dictionary(self.spec["dictionary"]).markerSize + 2)
            cols = nx - 1

            def clear(r, c):
                return sq if dark[r, c] else light_clear

            def border(r, c):
                return 0.0 if dark[r, c] else light_border

            for r in range(1, ny):
                for c in range(1, nx - 1):  # horizontal: corners (r, c) -> (r, c+1), squares above/below
                    a = (r - 1) * cols + (c - 1)
                    # start->end is +x; its left normal (-dy, dx) = +y points to row r (below).
                    out.append(EdgeSegment(f"h{r}_{c}", (c * sq, r * sq), ((c + 1) * sq, r * sq),
                                           clear_left_mm=clear(r, c), clear_right_mm=clear(r - 1, c),
                                           corner_ids=(a, a + 1), border_left_mm=border(r, c),
                                           border_right_mm=border(r - 1, c)))
            for c in range(1, nx):
                for r in range(1, ny - 1):  # vertical: corners (r, c) -> (r+1, c), squares left/right
                    a = (r - 1) * cols + (c - 1)
                    # start->end is +y; its left normal (-dy, dx) = -x points to column c - 1.
                    out.append(EdgeSegment(f"v{c}_{r}", (c * sq, r * sq), (c * sq, (r + 1) * sq),
                                           clear_left_mm=clear(r, c - 1), clear_right_mm=clear(r, c),
                                           corner_ids=(a, a + cols), border_left_mm=border(r, c - 1),
                                           border_right_mm=border(r, c)))
        elif self.kind == "slanted-edge":
            e = float(self.spec["edge_mm"])
            pts = [(0.0, 0.0), (e, 0.0), (e, e), (0.0, e)]
            for k, name in enumerate(("top", "right", "bottom", "left")):
                out.append(EdgeSegment(name, pts[k], pts[(k + 1) % 4], clear_left_mm=0.5 * e,
                                       clear_right_mm=0.5 * e, corner_ids=(k, (k + 1) % 4)))
        return out

    # ------------------------------------------------------------------ detection

    def detect(self, linear: np.ndarray, copies: list[np.ndarray] | None = None) -> Detection | None:
        """Find the target in a linear image; None when it is not there.

        The detectors run on 8-bit copies, linear and gamma-encoded (2.2); the one that finds
        the most corners wins (ArUco's adaptive threshold prefers linear contrast on blurred
        markers, dark scenes are better served by the gamma copy). ``copies``: those of
        :func:`detection_copies`, where the caller made them already (one image, many targets).
        """
        best = None
        for grey in copies if copies is not None else detection_copies(linear):
            if self.kind == "charuco":
                found = self._detect_charuco(grey)
            elif self.kind == "checkerboard":
                found = self._detect_checkerboard(grey)
            else:
                found = self._detect_square(grey)
            if found is not None and (best is None or len(found.ids) > len(best.ids)):
                best = found
            if best is not None and len(best.ids) >= self.corner_count():
                break  # every corner found: no other copy can find more (half the detector's time)
        return best

    def corner_count(self) -> int:
        """How many corners a detection can find at most (a whole board; a square's four)."""
        if self.kind == "slanted-edge":
            return 4
        nx, ny = self.spec["squares"]
        return (nx - 1) * (ny - 1)

    def _detect_charuco(self, grey):

        detector = _charuco_detector(self)
        corners, ids, _, _ = detector.detectBoard(grey)
        if ids is None or len(ids) < 4:
            return None
        ids = ids.ravel().astype(int)
        obj = self.inner_corners_mm()[ids]
        return Detection(self.id, obj, corners.reshape(-1, 2).astype(np.float64), ids)

    def _detect_checkerboard(self, grey):
        import cv2

        nx, ny = self.spec["squares"]
        ok, corners = cv2.findChessboardCornersSB(grey, (nx - 1, ny - 1), flags=cv2.CALIB_CB_EXHAUSTIVE
                                                  | cv2.CALIB_CB_ACCURACY)
        if not ok:
            return None
        ids = np.arange((nx - 1) * (ny - 1))
        return Detection(self.id, self.inner_corners_mm(), corners.reshape(-1, 2).astype(np.float64), ids)

    def _detect_square(self, grey):
        import cv2

        _, mask = cv2.threshold(grey, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
        contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        h, w = grey.shape
        best = None
        for cnt in contours:
            area = cv2.contourArea(cnt)
            if area < 400:
                continue
            x, y, bw, bh = cv2.boundingRect(cnt)
            if x <= 1 or y <= 1 or x + bw >= w - 1 or y + bh >= h - 1:
                continue  # cut by the frame (or a dark surround seen as a quad): not a whole square
            poly = cv2.approxPolyDP(cnt, 0.02 * cv2.arcLength(cnt, True), True)
            if len(poly) != 4 or not cv2.isContourConvex(poly) or (best is not None and area <= best[0]):
                continue
            if not _dark_on_light(grey, poly.reshape(4, 2)):
                continue
            best = (area, poly.reshape(4, 2).astype(np.float64))
        if best is None:
            return None
        quad = best[1]
        # Order: the corner nearest the top-left first, then clockwise in the image (x right, y down).
        centre = quad.mean(axis=0)
        ang = np.arctan2(quad[:, 1] - centre[1], quad[:, 0] - centre[0])
        quad = quad[np.argsort(ang)]
        start = int(np.argmin(quad.sum(axis=1)))
        quad = np.roll(quad, -start, axis=0)
        # The blurred outline sits half a blur width outside the edge; refine to the edge lines later.
        e = float(self.spec["edge_mm"])
        obj = np.array([[0, 0, 0], [e, 0, 0], [e, e, 0], [0, e, 0]], np.float64)
        return Detection(self.id, obj, quad, np.arange(4))


def _dark_on_light(grey: np.ndarray, quad: np.ndarray) -> bool:
    """Is the quadrilateral darker inside than in a ring around it (a dark square on a light
    ground, not a dark surround or a gap between light patches)?"""
    import cv2

    inside = np.zeros(grey.shape, np.uint8)
    cv2.fillConvexPoly(inside, quad.astype(np.int32), 1)
    size = max(3, int(0.15 * np.sqrt(cv2.contourArea(quad.astype(np.float32)))))
    grown = cv2.dilate(inside, np.ones((2 * size + 1, 2 * size + 1), np.uint8))
    core = cv2.erode(inside, np.ones((2 * size + 1, 2 * size + 1), np.uint8))
    ring = (grown > 0) & (cv2.dilate(inside, np.ones((5, 5), np.uint8)) == 0)
    if not ring.any() or not core.any():
        return False
    return float(np.median(grey[ring])) > float(np.median(grey[core > 0])) + 0.25 * float(np.ptp(grey))


@functools.lru_cache(maxsize=32)
def _detector_for(dictionary: str, squares: tuple, square_mm: float, marker_mm: float, legacy: bool,
                  thread: int = 0):
    """One detector per board and per thread (``lensfit.runtime.parallel`` searches images in threads;
    OpenCV does not promise that one detector object serves two threads at once)."""
    import cv2

    board = charuco_board(squares, square_mm, marker_mm, dictionary, legacy)
    return cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters())


def _charuco_detector(target: Target):
    s = target.spec
    return _detector_for(s["dictionary"], tuple(s["squares"]), float(s["square_mm"]), float(s["marker_mm"]),
                         bool(s.get("legacy_pattern", False)), threading.get_ident())
