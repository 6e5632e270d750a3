"""The thick-lens fit (pupil magnification P) against samples simulated from paraxial optics
written out here, independent of lensfit: the entrance pupil E (diameter A = f/N) images to
the exit pupil E' (diameter P A); an object at x from E images at x' from E' with
1/x' = 1/(P f) - 1/(P^2 x); the blur on a sensor at s_x = x'(X) is the exit-pupil cone's cross
section P A |s_x - x'| / x'; a pinhole calibration centred on E sees chief rays leave E' with
tan(theta') = tan(theta) / P, so it measures f_px = s_x / (P p).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lensfit.errors import InputError
from lensfit.fitting import fit as fit_any_lens


def fit(*args, **kw):
    """lensfit's fit of these ideal thick lenses (paraxial, no aberrations: the f-number is the
    blur's own; lensfit.fitting.nominal)."""
    return fit_any_lens(*args, **{"ideal_lens": True, **kw})

PITCH = 0.005


def image_distance(f, P, x):
    """x' from the exit pupil for an object at x from the entrance pupil (inf allowed)."""
    inv_x = 0.0 if math.isinf(x) else 1.0 / x
    return 1.0 / (1.0 / (P * f) - inv_x / P**2)


def simulate(f, P, settings, rng, *, noise_px=0.05, rel_noise=0.005, fpx_rel_sigma=1e-4, n=40):
    """Rows and per-setting calibrated f_px for settings {label: (N, X, (near, far))}."""
    rows, fpx, fsg = [], {}, {}
    for label, (N, X, (near, far)) in settings.items():
        A = f / N
        s_x = image_distance(f, P, X)
        for i, d in enumerate(1.0 / np.linspace(1.0 / near, 1.0 / far, n)):
            xi = image_distance(f, P, d)
            c = P * A * abs(s_x - xi) / xi / PITCH
            sigma = math.hypot(noise_px, rel_noise * c)
            rows.append({"setting": label, "distance_mm": float(d), "coc_diameter_px": abs(c + rng.normal(0, sigma)),
                         "sigma_px": sigma, "image": f"{label}_{i % 8}.png"})
        true_fpx = s_x / (P * PITCH)
        fpx[label] = true_fpx * (1 + fpx_rel_sigma * rng.normal())
        fsg[label] = fpx_rel_sigma * true_fpx
    return rows, fpx, fsg


def inside(est, truth):
    lo, hi = est.ci95
    return (lo is None or lo <= truth) and (hi is None or truth <= hi)


def check(est, truth, rel, k_sigma=3.0):
    """Within ``rel`` of the truth and within ``k_sigma`` of its stated sigma (one case; the
    95 % coverage over many cases is tested separately)."""
    assert est.value is not None, est.reason
    assert abs(est.value / truth - 1) <= rel, f"{est.value} vs {truth} ({100 * (est.value / truth - 1):+.2f}%)"
    assert abs(est.value - truth) <= k_sigma * est.sigma, f"{est.value} vs {truth}: {est.value - truth:+.3g} " \
        f"is more than {k_sigma} sigma ({est.sigma:.3g})"


BRACKETS = {
    "telephoto 135 mm P 0.55": (135.0, 0.55, {"near": (5.6, 1500.0, (900.0, 3000.0)),
                                               "far": (5.6, 4000.0, (2000.0, 9000.0))}),
    "retrofocus 24 mm P 2.1": (24.0, 2.1, {"near": (4.0, 400.0, (250.0, 900.0)),
                                            "mid": (4.0, 800.0, (450.0, 2000.0)),
                                            "far": (4.0, 2000.0, (900.0, 6000.0))}),
    "double Gauss 50 mm P 0.95": (50.0, 0.95, {"near": (2.8, 500.0, (350.0, 800.0)),
                                                "far": (2.8, 2000.0, (1000.0, 5000.0))}),
}


@pytest.mark.parametrize("name", list(BRACKETS))
def test_focus_bracket_recovers_pupil_magnification_and_the_lens(name):
    f, P, settings = BRACKETS[name]
    rows, fpx, fsg = simulate(f, P, settings, np.random.default_rng(7))
    r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
    assert r.ok, r.reasons
    assert r.pupil_magnification_source == "fitted"
    check(r.pupil_magnification, P, 0.05)
    check(r.focal_length_mm, f, 0.01)
    for label, (N, X, _) in settings.items():
        check(r.settings[label]["f_number"], N, 0.01)
        check(r.settings[label]["focus_distance_mm"], X, 0.01)
        check(r.settings[label]["sensor_distance_mm"], image_distance(f, P, X), 0.01)  # exit pupil to sensor
        e = r.settings[label]["focus_distance_from_sensor_mm"]
        assert e.value is None and "entrance pupil" in e.reason  # not determined by blur + pinhole


def test_thin_lens_mapping_of_a_telephoto_is_biased_as_predicted():
    """One setting of a P = 0.5 lens read as a thin lens (P = 1 given): f and N come out high by
    about (f/X)(1/P - 1) (thick lens: 1/f = 1/S + 1/(P X), lensfit.fitting notes)."""
    f, P, N, X = 100.0, 0.5, 4.0, 2000.0
    rows, fpx, fsg = simulate(f, P, {"a": (N, X, (1200.0, 5000.0))}, np.random.default_rng(3))
    r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, pupil_magnification=1.0,
                  focusing="unit")
    assert r.pupil_magnification_source == "assumed" and r.pupil_magnification.value == 1.0
    S = image_distance(f, P, X) / P
    f_thin = 1.0 / (1.0 / S + 1.0 / X)
    assert r.focal_length_mm.value == pytest.approx(f_thin, rel=2e-3)
    assert f_thin / f - 1 == pytest.approx((f / X) * (1 / P - 1), rel=0.1)
    assert not inside(r.focal_length_mm, f)  # the wrong assumption: a tight interval without the truth
    # the right assumption gives the lens back
    r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, pupil_magnification=P,
                focusing="unit")
    check(r.focal_length_mm, f, 0.003)
    check(r.settings["a"]["f_number"], N, 0.01)
    assert r.pupil_magnification_source == "assumed" and r.pupil_magnification.value == P


@pytest.mark.parametrize("P", [0.55, 0.75, 1.0, 1.54, 2.0, 4.7, 7.2])
def test_one_setting_carries_the_spread_of_photographic_lenses(P):
    """Without a given P, one setting cannot determine it: the fit carries the spread of
    photographic lenses (never an exact P = 1), so the 95 % intervals of f and N hold the truth
    of a telephoto, a normal lens and a retrofocus wide angle alike (up to the extreme ones, P 4.7
    and 7.2 among the surveyed designs, data_specs/f_number_survey.toml), P's own interval too,
    and the focus distance from the entrance pupil, which blur fixes whatever P is, stays as tight
    as with P known."""
    f, N, X = 35.0, 4.0, 700.0
    rows, fpx, fsg = simulate(f, P, {"a": (N, X, (400.0, 2000.0))}, np.random.default_rng(21))
    r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
    assert r.pupil_magnification_source == "prior" and "photographic lenses" in r.pupil_magnification.reason
    assert any("pupil magnification P not determined" in w for w in r.warnings)
    assert inside(r.focal_length_mm, f) and inside(r.settings["a"]["f_number"], N)
    assert inside(r.pupil_magnification, P)
    known = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, pupil_magnification=P,
                focusing="unit")
    check(r.settings["a"]["focus_distance_mm"], X, 0.01)
    assert r.settings["a"]["focus_distance_mm"].sigma < 1.2 * known.settings["a"]["focus_distance_mm"].sigma
    # the interval's width is what P's range moves f by, (f/X)|1/P - 1| from P = 0.46 to 2.5, not more
    lo, hi = r.focal_length_mm.ci95
    assert (hi - lo) / f < 1.5 * (f / X) * (1 / 0.46 - 1 / 2.5)


def test_a_prior_range_widens_the_intervals_honestly():
    f, P, N, X = 100.0, 0.6, 4.0, 1500.0
    rng = np.random.default_rng(11)
    rows, fpx, fsg = simulate(f, P, {"a": (N, X, (900.0, 4000.0))}, rng)
    fixed = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, pupil_magnification=1.0,
                  focusing="unit")
    ranged = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg,
                 pupil_magnification=(0.5, 2.0), focusing="unit")
    assert ranged.pupil_magnification_source == "prior"
    assert not inside(fixed.focal_length_mm, f)  # the silent thin-lens answer excludes the truth ...
    assert inside(ranged.focal_length_mm, f)  # ... the stated range holds it
    assert inside(ranged.settings["a"]["f_number"], N)
    assert ranged.focal_length_mm.sigma > 5 * fixed.focal_length_mm.sigma
    lo, hi = ranged.pupil_magnification.ci95
    # the data add nothing to the prior on P: its 95 % range (0.5, 2), widened a little by the
    # Student-t of the image jackknife (8 images)
    assert 0.4 < lo < 0.6 and 1.7 < hi < 2.5


def test_thin_lens_is_the_p_equal_1_case():
    f, N, X = 50.0, 2.8, 1500.0
    settings = {"a": (N, X, (800.0, 4000.0)), "b": (N, 3000.0, (1500.0, 8000.0))}
    rows, fpx, fsg = simulate(f, 1.0, settings, np.random.default_rng(5))
    auto = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
    check(auto.pupil_magnification, 1.0, 0.05)
    thin = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, pupil_magnification=1.0,
                  focusing="unit")
    check(thin.focal_length_mm, f, 0.002)
    e = thin.settings["a"]["focus_distance_from_sensor_mm"]  # the thin lens: E is the lens plane
    assert e.value == pytest.approx(X + image_distance(f, 1.0, X), rel=2e-3)


def test_settings_at_one_focus_distance_cannot_fit_p_and_say_so():
    f, P = 85.0, 0.8
    settings = {"f2": (2.0, 1500.0, (900.0, 4000.0)), "f4": (4.0, 1500.0, (900.0, 4000.0))}
    rows, fpx, fsg = simulate(f, P, settings, np.random.default_rng(9))
    r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
    assert r.pupil_magnification_source == "prior"
    assert any("pupil magnification" in w and "focus" in w for w in r.warnings)
    assert inside(r.focal_length_mm, f)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf, 50.0, (2.0, 1.0), (0.0, 1.0), "x"])
def test_bad_pupil_magnification_is_refused(bad):
    rows, fpx, fsg = simulate(50.0, 1.0, {"a": (2.8, 1500.0, (800.0, 4000.0))}, np.random.default_rng(1))
    with pytest.raises(InputError, match="pupil_magnification"):
        fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, pupil_magnification=bad)


def test_intervals_of_p_f_and_n_cover_the_truth():
    """Over 30 noise draws of the telephoto bracket, the 95 % intervals hold the truth 80-100 %
    of the time (a binomial 95 % band around 95 % for 30 draws reaches down to about 83 %)."""
    f, P, settings = BRACKETS["telephoto 135 mm P 0.55"]
    hits = {"P": 0, "f": 0, "N": 0, "X": 0}
    draws = 30
    for seed in range(draws):
        rows, fpx, fsg = simulate(f, P, settings, np.random.default_rng(100 + seed), n=24)
        r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
        hits["P"] += inside(r.pupil_magnification, P)
        hits["f"] += inside(r.focal_length_mm, f)
        hits["N"] += inside(r.settings["far"]["f_number"], settings["far"][0])
        hits["X"] += inside(r.settings["far"]["focus_distance_mm"], settings["far"][1])
    assert all(h >= 0.8 * draws for h in hits.values()), hits


def test_a_refused_bracket_says_how_wide_a_bracket_determines_p_to_5_percent():
    """A bracket too narrow for P is refused with the spread of inverse focus distances that
    would give P to 5 %; a bracket that wide, simulated with the same calibration precision,
    does recover P within 5 % in most noise draws (2 sigma: about 95 %)."""
    import re

    f, P, N, X_far, cal = 50.0, 1.07, 8.0, 2000.0, 0.003
    narrow = {"near": (N, 1500.0, (900.0, 3000.0)), "far": (N, X_far, (1000.0, 6000.0))}
    rows, fpx, fsg = simulate(f, P, narrow, np.random.default_rng(5), fpx_rel_sigma=cal)
    r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
    assert r.pupil_magnification_source == "prior"
    said = next(w for w in r.warnings if "pupil magnification" in w)
    need_per_m = float(re.search(r"P to 5 % \(2 sigma\) about ([0-9.e+]+) /m", said).group(1))
    X_near = 1.0 / (1.0 / X_far + need_per_m / 1000.0)
    assert X_near < 1500.0
    wide = {"near": (2 * N, X_near, (0.6 * X_near, 2.5 * X_near)), "far": (N, X_far, (1000.0, 6000.0))}
    within, draws = 0, 20
    for seed in range(draws):
        rows, fpx, fsg = simulate(f, P, wide, np.random.default_rng(200 + seed), fpx_rel_sigma=cal)
        r = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
        assert r.pupil_magnification_source == "fitted", r.warnings
        within += abs(r.pupil_magnification.value / P - 1) <= 0.05
    assert within >= 0.8 * draws, within


def test_an_internally_focusing_bracket_is_fitted_setting_by_setting(tmp_path):
    """A lens that focuses by moving a group inside breathes: f (and P) differ per setting. With
    the focusing unknown (the default) each setting is fitted by itself: its f and N within 1 %
    and their 95 % intervals holding its truth (the focus distance within 3 sigma); forced to share f (focusing = "unit"), the
    settings give one f that misses each setting's own."""
    rng = np.random.default_rng(31)
    per = {"near": (47.4, 0.94, 3.8, 600.0, (350.0, 1500.0)), "mid": (48.4, 1.01, 3.9, 1000.0, (550.0, 2500.0)),
           "far": (49.0, 1.06, 3.9, 1600.0, (800.0, 4500.0))}
    rows, fpx, fsg = [], {}, {}
    for label, (f, P, N, X, span) in per.items():
        r, fp, fs = simulate(f, P, {label: (N, X, span)}, rng, fpx_rel_sigma=1e-3)
        rows += r
        fpx.update(fp)
        fsg.update(fs)
    from lensfit.calibration.camera import Intrinsics
    from lensfit.io.samples import Sample, SampleTable

    table = SampleTable(samples=[Sample(r_["image"], r_["setting"], "board", "e", r_["distance_mm"], r_["distance_mm"],
                                        r_["distance_mm"], r_["coc_diameter_px"], r_["sigma_px"], "edge", "",
                                        (0.0, 0.0), (1.0, 0.0), "pose") for r_ in rows],
                        intrinsics={k: Intrinsics(fpx[k], (0.0, 0.0), (0.0,) * 5, 0.1, 8, "manifest", fsg[k])
                                    for k in fpx}, pixel_pitch_mm=PITCH)
    r = fit(table)
    assert r.focal_length_mm.value is None and "own" in r.focal_length_mm.reason
    for label, (f, P, N, X, _) in per.items():
        est = r.settings[label]
        assert inside(est["focal_length_mm"], f) and inside(est["f_number"], N)
        check(est["focus_distance_mm"], X, 0.01)
        assert abs(est["focal_length_mm"].value / f - 1) < 0.01 and abs(est["f_number"].value / N - 1) < 0.01
    assert any("were the lens to focus as a unit" in w for w in r.warnings)
    # its report and results file say so (no shared f, no shared P) and hold finite numbers or null
    import json

    from lensfit.fitting import results_document
    from lensfit.outputs.report import write_fit_report

    document = results_document(r)
    assert document["focal_length_mm"]["value"] is None and document["pupil_magnification"]["value"] is None
    json.dumps(document, allow_nan=False)
    report = tmp_path / "report.html"
    write_fit_report(report, r, document, table)
    assert "P how the lens focuses is not known" in report.read_text()
    unit = fit(rows, pixel_pitch_mm=PITCH, focal_length_px=fpx, focal_length_sigma_px=fsg, focusing="unit")
    assert unit.focal_length_mm.value is not None
    assert sum(abs(unit.focal_length_mm.value / f - 1) > 0.005 for f, *_ in per.values()) >= 2
