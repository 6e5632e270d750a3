"""Which reading the fit takes where a sample gives two (lensfit.fitting.refits): the spot's second
moment through the shaped-spot model, or the uniform disk's reading of the same edge.

Samples are simulated here from the thin-lens V: each edge's "shaped" reading is the true blur,
its "disk" reading 4 % larger (what an unmodelled Airy pattern's tails do to one kind and not the
other is beside the point here: the test is which of the two the fit uses, and when).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lensfit.errors import InputError
from lensfit.fitting import fit


def rows(f_mm, n, x_mm, pitch, flags="shaped_spot", seed=0):
    rng = np.random.default_rng(seed)
    s = 1.0 / (1.0 / f_mm - 1.0 / x_mm)
    out = []
    for i in range(8):
        for d in x_mm * np.exp(np.linspace(-0.7, 0.9, 12) + 0.01 * i):
            c = (f_mm / n) * s * abs(1.0 / x_mm - 1.0 / d) / pitch
            sigma = math.hypot(0.03, 0.005 * c)
            c_obs = abs(c + sigma * rng.normal())
            out.append({"setting": "a", "image": f"i{i}.png", "distance_mm": float(d), "coc_diameter_px": c_obs,
                        "sigma_px": sigma, "flags": flags, "disk_diameter_px": 1.04 * c_obs,
                        "disk_sigma_px": 1.04 * sigma})
    return out, s / pitch


def as_disk(rs):
    """The same rows with the disk's readings in place of the shaped ones, written out here."""
    return [{**r, "coc_diameter_px": r["disk_diameter_px"], "sigma_px": r["disk_sigma_px"], "flags": "",
             "disk_diameter_px": None, "disk_sigma_px": None} for r in rs]


def n_of(result):
    return result.settings["a"]["f_number"].value


@pytest.mark.parametrize("pitch,n,airy_large", [(0.004, 11.0, True), (0.01, 2.8, False)])
def test_auto_takes_the_disk_only_where_an_untested_airy_pattern_would_matter(pitch, n, airy_large):
    # Airy scale 550 nm x N_w / p: 1.5 px at f/11 on 4 um pixels; 0.15 px at f/2.8 on 10 um.
    rs, fpx = rows(50.0, n, 2000.0, pitch)
    kw = dict(pixel_pitch_mm=pitch, focal_length_px=fpx, focal_length_sigma_px=0.0, ideal_lens=True)
    shaped, disk, auto = (fit(rs, spot_shape=m, **kw) for m in ("shaped", "disk", "auto"))
    assert n_of(disk) == pytest.approx(n_of(fit(as_disk(rs), **kw)), rel=1e-9)
    assert n_of(shaped) == pytest.approx(n, rel=0.01) and n_of(disk) == pytest.approx(n / 1.04, rel=0.01)
    assert n_of(auto) == n_of(disk if airy_large else shaped)
    assert any("shapes were not used" in w for w in auto.warnings) == airy_large
    # Images the pipeline tested and found without an Airy pattern keep their shapes.
    tested = [{**r, "flags": "shaped_spot;airy_not_seen"} for r in rs]
    assert n_of(fit(tested, **kw)) == pytest.approx(n_of(shaped), rel=1e-9)


def test_a_bad_mode_is_refused():
    rs, fpx = rows(50.0, 8.0, 2000.0, 0.005)
    with pytest.raises(InputError, match="spot_shape"):
        fit(rs, pixel_pitch_mm=0.005, focal_length_px=fpx, spot_shape="round")


def test_auto_takes_the_disk_only_on_the_settings_where_the_pattern_would_matter():
    # A bracket on 4 um pixels: f/2.8 (Airy scale 0.4 px) and f/11 (1.5 px).
    wide, fpx = rows(50.0, 2.8, 2000.0, 0.004)
    narrow, _ = rows(50.0, 11.0, 1000.0, 0.004, seed=1)
    both = wide + [{**r, "setting": "b", "image": "b" + r["image"]} for r in narrow]
    kw = dict(pixel_pitch_mm=0.004, focal_length_px={"a": fpx, "b": 1.0 / (1 / 50.0 - 1 / 1000.0) / 0.004},
              focal_length_sigma_px=0.0, ideal_lens=True)
    auto = fit(both, **kw)
    assert auto.settings["a"]["f_number"].value == pytest.approx(2.8, rel=0.01)  # the shapes
    assert auto.settings["b"]["f_number"].value == pytest.approx(11.0 / 1.04, rel=0.01)  # the disk
    assert any("'b'" in w and "'a'" not in w for w in auto.warnings if "shapes were not used" in w)
