"""The edge estimator's window across an edge: each side as wide as its own clean room allows.

On a ChArUco board a marker sits a few pixels beside one side of many edges, the other side
clear. The spot is a shipped design's real-ray spot (retrofocus-24 at f/4, beyond its focus: a
core in a halo), traced by synth's tracer (checked against optiland's in tests/synth/test_lens.py);
its hits, projected across the edge and averaged over 8 x 8 points of each pixel, make an exact
image of the edge and the marker's edge beside it. The reference is the spot's own second-moment
diameter, 4 sigma of the hits across the edge.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lensfit.estimators.base import EdgeTask
from lensfit.estimators.edge import measure
from lensfit.estimators.profile import window_wanted, windows
from helpers import axial_spot_hits


def board_edge(hits: np.ndarray, marker_px: float, noise: float, angle_deg: float = 0.5, size=(120, 160)):
    """A dark-to-light edge blurred by the spot whose hits lie at ``hits`` across it, a dark
    marker ``marker_px`` beyond it on the light side, the dark side clear; the task states that."""
    hits = np.sort(hits - hits.mean())
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    a = math.radians(angle_deg)
    normal = np.array([math.cos(a), -math.sin(a)])  # towards the light side
    centre = np.array([w / 2, h / 2])
    share = lambda t: np.searchsorted(hits, t.ravel()).reshape(h, w) / len(hits)  # noqa: E731
    light = np.zeros((h, w))
    k = 8
    for i in range(k):
        for j in range(k):
            t = (xx + (i + 0.5) / k - 0.5 - centre[0]) * normal[0] + (yy + (j + 0.5) / k - 0.5 - centre[1]) * normal[1]
            light += share(t) - share(t - marker_px)
    image = 0.1 + 0.7 * light / k**2 + noise * np.random.default_rng(0).standard_normal((h, w))
    along = np.array([-normal[1], normal[0]])
    # left of start -> end is the side of (-dy, dx): here the dark side, clear for 70 px
    return image, EdgeTask(centre - 45 * along, centre + 45 * along, 70.0, marker_px)


@pytest.fixture(scope="module")
def halo_spot():
    """Hits across the edge (px) of the retrofocus's spot 1.6 x beyond its focus, scaled to 4 px."""
    from synth.lens.files import load_prescription

    x, = axial_spot_hits(load_prescription("retrofocus-24").with_f_number(4.0), 25.0, (1.6,))
    return x / (np.std(x))  # 4 sigma = 4 px


def test_a_marker_beside_one_side_narrows_that_side_alone():
    task = EdgeTask(np.zeros(2), np.array([0.0, 90.0]), 70.0, 7.0)
    (right, left), margin, truncated = windows(task, 2.0)
    assert left == pytest.approx(window_wanted(2.0))  # the clear side: all the spot asks for
    assert right == pytest.approx(7.0 - 0.5 - 2.0)  # the marker's side: its clean room less the spot
    assert margin == pytest.approx(left + 2.0 + 1.0) and not truncated


def test_a_core_in_a_halo_beside_a_marker_reads_its_second_moment(halo_spot):
    """4 px, the marker 7 px away: read within 1.5 % and 3 sigma of the exact second moment (with
    the marker's side setting both sides' width, the halo cut on the clear side too: 0.890 +-
    0.030 of it)."""
    image, task = board_edge(halo_spot, 7.0, 0.003)
    r = measure(image, [task])[0]
    assert r.coc_diameter_px is not None, r.flags
    err = r.coc_diameter_px - 4.0
    assert abs(err) < 0.015 * 4.0 and abs(err) < 3.0 * r.sigma_px, (r.coc_diameter_px, r.sigma_px, r.flags)
