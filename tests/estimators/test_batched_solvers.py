"""The batched Levenberg-Marquardt (lensfit.fitting.lm) against scipy's independent solver and analytic
minima, and the trace store (lensfit.runtime.jaxcache): same numbers with it, without it, from its stored
executables (in a new process too) and from corrupted files."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares as scipy_least_squares

from lensfit.runtime import jaxcache

from lensfit.fitting import lm


def _rosenbrock(theta, args):
    x, y = theta[0], theta[1]
    return jnp.stack([1.0 - x, 10.0 * (y - x * x)])


def test_rosenbrock_reaches_the_analytic_minimum():
    with jax.enable_x64(True):
        theta, cost, ok = lm.least_squares(_rosenbrock, jnp.array([-1.2, 1.0]), None, max_steps=200,
                                           rtol=1e-12, atol=1e-14)
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(theta), [1.0, 1.0], atol=1e-8)
    assert float(cost) < 1e-16


def _decay(theta, args):
    t, y, w = args
    # Parameters on scales 1e5 apart: amplitude ~1e4, rate ~0.1 per unit, offset ~1.
    return w * (theta[0] * jnp.exp(-theta[1] * t) + theta[2] - y)


def test_batched_fits_equal_scipy_on_badly_scaled_problems():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 40.0, 60)
    truths = np.column_stack([rng.uniform(5e3, 2e4, 12), rng.uniform(0.05, 0.3, 12), rng.uniform(0.5, 2.0, 12)])
    ys = np.array([a * np.exp(-k * t) + c for a, k, c in truths]) + rng.normal(0, 5.0, (12, t.size))
    w = np.full(t.size, 1.0 / 5.0)
    start = np.array([1e4, 0.1, 1.0])
    with jax.enable_x64(True):
        solve = jax.jit(jax.vmap(lambda y: lm.least_squares(_decay, jnp.asarray(start), (jnp.asarray(t), y,
                                                                                          jnp.asarray(w)),
                                                            max_steps=100, rtol=1e-12, atol=1e-14)))
        theta, cost, ok = (np.asarray(a) for a in solve(jnp.asarray(ys)))
    assert ok.all()
    for i in range(len(ys)):
        ref = scipy_least_squares(lambda p: w * (p[0] * np.exp(-p[1] * t) + p[2] - ys[i]), start, method="lm",
                                  xtol=1e-15, ftol=1e-15, gtol=1e-15)
        # Equal to within 1e-4 of each parameter's standard error (the precision a minimum has).
        sigma = np.sqrt(np.diag(np.linalg.inv(ref.jac.T @ ref.jac)))
        assert np.all(np.abs(theta[i] - ref.x) < 1e-4 * sigma)
        assert cost[i] == pytest.approx(2 * ref.cost, rel=1e-9)  # scipy's cost is half the sum of squares


def test_a_parameter_the_data_do_not_determine_stays_put_with_a_huge_variance():
    def residuals(theta, args):
        return jnp.stack([theta[0] - 3.0, 2.0 * (theta[0] - 3.0), 0.0 * theta[1]])

    with jax.enable_x64(True):
        theta, cost, ok = lm.least_squares(residuals, jnp.array([0.0, 0.7]), None, max_steps=50)
        cov = np.asarray(lm.covariance(jax.jacfwd(residuals)(theta, None)))
    assert bool(ok) and np.isfinite(np.asarray(theta)).all()
    assert float(theta[0]) == pytest.approx(3.0, abs=1e-10)
    assert float(theta[1]) == 0.7
    assert cov[0, 0] == pytest.approx(1.0 / 5.0, rel=1e-6)  # 1 / sum of squared derivatives
    assert cov[1, 1] > 1e100  # undetermined: no false precision (a pseudo-inverse would say 0)


def _affine(x, scale, shift: float):
    return {"y": scale * x + shift, "sum": jnp.sum(x)}


def test_trace_store_gives_the_same_numbers_and_survives_broken_files(tmp_path):
    x = jnp.arange(6.0)
    plain = _affine(x, 2.0, shift=1.0)

    def in_a_new_process(shift=1.0):
        jaxcache.set_store(tmp_path)  # nothing loaded yet
        return jaxcache.call("affine", _affine, (x, 2.0), {"shift": shift}, ("tests.test_batched_solvers",))

    try:
        first = in_a_new_process()
        traces, executables = list(tmp_path.glob("affine-*.jaxexport")), list(tmp_path.glob("affine-*.jaxexe"))
        assert len(traces) == 1 and len(executables) == 1  # traced, compiled and stored once
        loaded = in_a_new_process()  # the executable
        executables[0].write_bytes(b"not an executable")
        recompiled = in_a_new_process()  # from the stored trace, the executable stored again
        assert executables[0].read_bytes() != b"not an executable"
        executables[0].unlink()
        traces[0].write_bytes(b"not an export")
        broken = in_a_new_process()  # traced afresh
        other = jaxcache.call("affine", _affine, (x, 2.0), {"shift": 5.0}, ("tests.test_batched_solvers",))
        # an executable that loads but does not run with these arguments (one for 3 values, not
        # 6): its first call fails, the file goes, and the traced function answers
        before = set(tmp_path.glob("affine-*.jaxexe"))
        short = jaxcache.call("affine", _affine, (jnp.arange(3.0), 2.0), {"shift": 1.0},
                              ("tests.test_batched_solvers",))
        (short_exe,) = set(tmp_path.glob("affine-*.jaxexe")) - before
        executables[0].write_bytes(short_exe.read_bytes())
        mismatched = in_a_new_process()
        assert not executables[0].exists()  # removed after its first call failed
    finally:
        jaxcache.set_store(None)
    for got in (first, loaded, recompiled, broken, mismatched):
        np.testing.assert_array_equal(np.asarray(got["y"]), np.asarray(plain["y"]))
        assert float(got["sum"]) == float(plain["sum"])
    np.testing.assert_array_equal(np.asarray(other["y"]), 2.0 * np.arange(6.0) + 5.0)  # the static argument keys it
    np.testing.assert_array_equal(np.asarray(short["y"]), 2.0 * np.arange(3.0) + 1.0)
    assert traces[0].read_bytes() != b"not an export"  # the broken file was traced afresh


_LAPACK_SCRIPT = """
import json, sys
from pathlib import Path
import jax, jax.numpy as jnp, numpy as np
from lensfit.runtime import jaxcache

def solve(a, b):
    return {"x": jnp.linalg.solve(a, b), "s": jnp.linalg.svd(a, compute_uv=False), "c": jnp.linalg.cholesky(a @ a.T)}

jaxcache.set_store(Path(sys.argv[1]))
a = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
b = np.array([1.0, 2.0, 3.0])
with jax.enable_x64(True):
    out = jaxcache.call("lapack", solve, (a, b), {}, ())
print(json.dumps({k: np.asarray(v).tolist() for k, v in out.items()}))
"""


def test_a_stored_executable_that_calls_lapack_runs_in_a_new_process(tmp_path):
    """The solvers' linear algebra calls LAPACK's kernels, which a loaded executable finds only
    once they are prepared (without that, a second process segfaulted): each run is its own
    process, the first compiling and storing, the second loading the executable."""
    import json
    import subprocess
    import sys

    script = tmp_path / "lapack.py"
    script.write_text(_LAPACK_SCRIPT)
    runs = [subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    assert len(list(tmp_path.glob("lapack-*.jaxexe"))) == 1
    a = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
    for run in runs:
        assert run.returncode == 0, run.stderr[-2000:]
        got = json.loads(run.stdout.strip().splitlines()[-1])
        np.testing.assert_allclose(got["x"], np.linalg.solve(a, [1.0, 2.0, 3.0]), rtol=1e-12)
        np.testing.assert_allclose(got["s"], np.linalg.svd(a, compute_uv=False), rtol=1e-12)
        np.testing.assert_allclose(got["c"], np.linalg.cholesky(a @ a.T), rtol=1e-12)


_NO_KERNELS_SCRIPT = """
import json, sys
from pathlib import Path
import jax.numpy as jnp, numpy as np
from lensfit.runtime import jaxcache

def scale(x):
    return {"y": 3.0 * x}

def solve(a, b):
    return {"y": jnp.linalg.solve(a, b)}

jaxcache.set_store(Path(sys.argv[1]))
a = np.array([[4.0, 1.0], [1.0, 3.0]], np.float32)
b = np.array([1.0, 2.0], np.float32)
out = {"scale": np.asarray(jaxcache.call("scale", scale, (b,), {}, (), kernels=False)["y"]).tolist()}
linalg_for_scale = "scipy.linalg" in sys.modules
if sys.argv[2] == "both":
    out["solve"] = np.asarray(jaxcache.call("solve", solve, (a, b), {}, (), kernels=False)["y"]).tolist()
print(json.dumps({**out, "scipy_linalg": linalg_for_scale}))
"""


def test_an_executable_declared_without_lapack_loads_without_preparing_it(tmp_path):
    """``kernels=False`` (the ray tracer): the executable is kept and a new process loads it without
    importing SciPy's linear algebra; a function so declared that does solve a linear system is
    not kept as an executable (a loaded one would find no LAPACK) and still answers right."""
    import json
    import subprocess
    import sys

    script = tmp_path / "no_kernels.py"
    script.write_text(_NO_KERNELS_SCRIPT)
    store = tmp_path / "store"
    store.mkdir()
    runs = [subprocess.run([sys.executable, str(script), str(store), mode], capture_output=True, text=True,
                           timeout=300) for mode in ("both", "both", "scale")]
    assert len(list(store.glob("scale-*.jaxexe"))) == 1 and not list(store.glob("solve-*.jaxexe"))
    for run in runs:
        assert run.returncode == 0, run.stderr[-2000:]
    got = [json.loads(run.stdout.strip().splitlines()[-1]) for run in runs]
    for g in got:
        np.testing.assert_allclose(g["scale"], [3.0, 6.0])
    for g in got[:2]:
        np.testing.assert_allclose(g["solve"], np.linalg.solve([[4.0, 1.0], [1.0, 3.0]], [1.0, 2.0]), rtol=1e-6)
    assert got[2]["scipy_linalg"] is False  # the stored executable loaded, LAPACK never prepared


def _edge_image(radius_px: float, angle_deg: float, size: int = 96):
    """A step edge through the image centre blurred by a disk, from brute-force sub-pixel
    sampling of the disk's edge-spread function (independent of lensfit.measurement.psf)."""
    from lensfit.estimators import EdgeTask

    a = np.radians(angle_deg)
    n = np.array([np.cos(a), np.sin(a)])
    q = (np.arange(8) + 0.5) / 8 - 0.5
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    img = np.zeros((size, size))
    for dy in q:
        for dx in q:
            d = (xx + dx - size / 2) * n[0] + (yy + dy - size / 2) * n[1]
            x = np.clip(d / radius_px, -1, 1)
            img += 0.1 + 0.8 * (0.5 + (x * np.sqrt(1 - x * x) + np.arcsin(x)) / np.pi)
    img /= q.size ** 2
    t = np.array([-n[1], n[0]])
    c = np.array([size / 2, size / 2])
    task = EdgeTask(c - 30 * t, c + 30 * t, 40.0, 40.0)
    return img, task


def test_a_stack_batched_in_one_solve_reads_each_edge_as_alone():
    from lensfit.estimators import edge

    cases = [_edge_image(r, ang) for r, ang in ((2.0, 7.0), (5.5, 33.0), (9.0, 61.0))]
    together = edge.measure_images([(lambda im=im: im, [task]) for im, task in cases])
    for (im, task), batch, r in zip(cases, together, (2.0, 5.5, 9.0)):
        alone = edge.measure(im, [task])[0]
        assert batch[0].coc_diameter_px == pytest.approx(alone.coc_diameter_px, rel=1e-9)
        assert batch[0].sigma_px == pytest.approx(alone.sigma_px, rel=1e-6)
        assert alone.coc_diameter_px == pytest.approx(2 * r, rel=0.02)


def test_a_sharp_edge_reads_sub_pixel_and_noise_without_an_edge_reads_nothing():
    from lensfit.estimators import edge

    sharp, task = _edge_image(0.02, 7.0)  # slanted: the pixel phases sample the profile finely
    got = edge.measure(sharp, [task])[0]
    assert got.coc_diameter_px is not None and got.coc_diameter_px < 0.5
    assert "sub_pixel_blur" in got.flags and got.sigma_px == pytest.approx(0.2)
    # Along a pixel axis through pixel centres a disk up to 1 px never reaches the next pixel:
    # any c below 1 px fits the same, and the reading must say so rather than give a number.
    aligned, task0 = _edge_image(0.02, 0.0)
    got = edge.measure(aligned, [task0])[0]
    assert got.coc_diameter_px is None and "blur_undetermined" in got.flags
    # Flat grey with noise: no edge to read. Whatever the solver lands on, no confident number.
    rng = np.random.default_rng(7)
    flat = 0.5 + rng.normal(0.0, 0.01, sharp.shape)
    for est in edge.measure(flat, [task]):
        assert est.coc_diameter_px is None or est.sigma_px > est.coc_diameter_px or "low_contrast" in est.flags


def test_queued_chunks_give_each_profile_its_own_reading():
    """The edge fits' queue (lensfit.estimators.edge_fit.FitQueue) dispatches a chunk as soon as
    it fills, per profile size, and moves a small size's last partial chunk up a size: 37 profiles
    of two sizes, in mixed order, must each come back with their own disk's radius (exact
    profiles, so the truth is known) and as fitted alone; a result given to the wrong problem, or
    a problem left out of a chunk, fails."""
    from lensfit.estimators.edge_fit import CHUNK, SMALL_CHUNK, fit_profiles
    from lensfit.measurement.psf import pixel_edge_profile

    rng = np.random.default_rng(11)
    profiles, radii = [], []
    for k in range(37):
        radius = float(rng.uniform(0.8, 6.0))
        bins = 48 if k % 3 else 200  # 64-bin and 256-bin problems, interleaved
        d = np.linspace(-(radius + 4.0), radius + 4.0, bins)
        angle = float(rng.uniform(0.1, 1.4))
        nx, ny = float(np.cos(angle)), float(np.sin(angle))
        with jax.enable_x64(True):
            level = np.asarray(pixel_edge_profile(jnp.asarray(d), radius, nx, ny))
        v = 0.1 + 0.7 * level + rng.normal(0.0, 1e-4, bins)
        profiles.append((d, np.zeros(bins), v, np.full(bins, 1e-4), (nx, ny)))
        radii.append(radius)
    assert len(profiles) > 2 * CHUNK and SMALL_CHUNK < CHUNK  # several chunks of each kind
    together = fit_profiles(profiles, False)
    for k in (0, 1, 2, 17, 36):
        alone = fit_profiles([profiles[k]], False)[0]
        np.testing.assert_allclose(together[k][0], alone[0], rtol=1e-9, atol=1e-12)
    for (theta, _, _, ok, _), radius in zip(together, radii):
        assert ok and np.sqrt(theta[1]) == pytest.approx(radius, rel=2e-3)
    disks = [t[0] for t in together]
    shaped = fit_profiles(profiles, True, disks)  # two disks, chunks of SMALL_CHUNK, from each one's disk
    for k in (3, 20, 36):
        alone = fit_profiles([profiles[k]], True, [disks[k]])[0]
        np.testing.assert_allclose(shaped[k][0], alone[0], rtol=1e-9, atol=1e-12)
    for (theta, _, _, ok, _), radius in zip(shaped, radii):
        m = 1.0 - theta[5] * (1.0 - (1.0 / (1.0 + np.exp(-theta[6]))) ** 2)
        assert ok and np.sqrt(theta[1] * m) == pytest.approx(radius, rel=1e-2)
