"""Field curvature: a lens whose sharp image surface is curved focuses the edge of the field at
another distance than the centre. Samples are simulated here from thin-lens ray geometry written
out independently of lensfit: the rays from an object point at depth d and field tangent t
converge at ``z = x'(d) + h^2 / (2 R)`` behind the lens (``x'`` the paraxial image distance,
``h = s t`` the image height, ``R`` the radius of the sharp surface), and the blur on the flat
sensor at ``s`` is the cone's cross-section ``A |s - z| / z``. To first order an off-axis point
then behaves as one at inverse distance ``1/d + t^2 / (2 R)``, so the in-focus inverse distance
moves by ``-t^2 / (2 R)``: the fit's ``kappa`` in dioptres is ``-1000 / (2 R)``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lensfit.errors import InputError
from lensfit.fitting import fit

PITCH = 0.005
F, N, X = 50.0, 4.0, 2000.0
S = 1.0 / (1.0 / F - 1.0 / X)  # lens to sensor


def simulate(R_mm, rng, *, n=240, noise_px=0.05, rel_noise=0.005, tan_max=0.12, field=True):
    """Rows of one setting "a": fronto-parallel edges at depths from X/2 to 3X, spread over the
    field out to ``tan_max`` (``R_mm`` inf: a flat field)."""
    rows = []
    for i in range(n):
        d = 1.0 / rng.uniform(1.0 / (3.0 * X), 2.0 / X)
        t = tan_max * math.sqrt(rng.uniform())
        h = S * t
        z = 1.0 / (1.0 / F - 1.0 / d) + (0.0 if math.isinf(R_mm) else h * h / (2.0 * R_mm))
        c = (F / N) * abs(S - z) / z / PITCH
        sigma = math.hypot(noise_px, rel_noise * c)
        row = {"setting": "a", "distance_mm": float(d), "coc_diameter_px": abs(c + rng.normal(0.0, sigma)),
               "sigma_px": sigma, "image": f"shot_{i % 12}.png"}
        if field:
            row["field_radius_px"] = h / PITCH
        rows.append(row)
    return rows


def run(rows, mode="auto"):
    return fit(rows, pixel_pitch_mm=PITCH, focal_length_px=S / PITCH, focal_length_sigma_px=1e-4 * S / PITCH,
               field_curvature=mode, ideal_lens=True)


def inside(est, truth):
    lo, hi = est.ci95
    return (lo is None or lo <= truth) and (hi is None or truth <= hi)


@pytest.mark.parametrize("R_mm", [-300.0, 400.0])
def test_a_curved_field_is_fitted_and_the_focus_distance_is_the_one_on_the_axis(R_mm):
    """Curved either way (4-5 % of 1/X at the field's edge): kappa comes out within 15 % of
    -1000 / (2 R) and the focus distance within 0.3 % of the axial X, inside its interval; the
    flat-field model (``off``) misses X by more than its own 95 % interval."""
    rng = np.random.default_rng(3)
    rows = simulate(R_mm, rng)
    r = run(rows)
    kappa = r.settings["a"]["field_curvature_per_m"]
    assert kappa.value is not None, kappa.reason
    assert kappa.value == pytest.approx(-1000.0 / (2.0 * R_mm), rel=0.15)
    x = r.settings["a"]["focus_distance_mm"]
    assert abs(x.value / X - 1) < 0.003 and inside(x, X), (x.value, x.ci95)
    assert r.settings["a"]["f_number"].value == pytest.approx(N, rel=0.01)
    flat = run(rows, "off").settings["a"]["focus_distance_mm"]
    assert not inside(flat, X), (flat.value, flat.ci95)


def test_a_flat_field_gives_the_thin_lens_fit_exactly():
    """No curvature in the data: ``auto`` finds kappa insignificant and returns the fit of
    ``off``, parameter for parameter; ``on`` fits it (within 3 sigma of 0) at some cost in the
    focus distance's sigma."""
    rows = simulate(math.inf, np.random.default_rng(5))
    auto, off, on = run(rows), run(rows, "off"), run(rows, "on")
    assert np.array_equal(auto.parameters, off.parameters)
    assert auto.settings["a"]["field_curvature_per_m"].value is None
    assert "not significant" in auto.settings["a"]["field_curvature_per_m"].reason
    k = on.settings["a"]["field_curvature_per_m"]
    assert abs(k.value) < 3 * k.sigma
    assert on.settings["a"]["focus_distance_mm"].sigma > off.settings["a"]["focus_distance_mm"].sigma


def test_focus_distance_intervals_cover_the_truth_under_field_curvature():
    """Over 30 noise draws of a curved field, the 95 % interval of the (axial) focus distance
    holds X in at least 26 (binomially, a true 95 % gives 26 or more in 98 % of such runs)."""
    rng = np.random.default_rng(11)
    hits = sum(inside(run(simulate(-300.0, rng, n=120)).settings["a"]["focus_distance_mm"], X) for _ in range(30))
    assert hits >= 26, hits


def test_without_field_radii_the_curvature_is_not_fitted_and_says_why():
    r = run(simulate(-300.0, np.random.default_rng(2), field=False), "on")
    assert r.settings["a"]["field_curvature_per_m"].value is None
    assert "field_radius_px" in r.settings["a"]["field_curvature_per_m"].reason


def test_a_bad_field_curvature_mode_is_refused():
    with pytest.raises(InputError, match="field_curvature"):
        run(simulate(-300.0, np.random.default_rng(2), n=20), "yes")


def test_a_bad_field_radius_is_refused_by_name():
    rows = simulate(-300.0, np.random.default_rng(2), n=20)
    rows[3]["field_radius_px"] = -4.0
    with pytest.raises(InputError, match=r"samples\[3\]\.field_radius_px"):
        run(rows)

