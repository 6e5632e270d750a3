"""Benchmark suites: estimated versus true lens parameters, and what accuracy costs in time.

A suite (``data_specs/bench/NAME.toml``, schema ``bench.schema.json``) is a grid:
scenes x render settings x effects x noise levels x estimators x solver settings x seeds. The
work is split into tasks, one per (scene, render setting, effects, seed), run in groups of one
(scene, render setting, seed) that share their geometric renders (each shot ray-traced or
convolved once for all the effects sets; a task that takes its images from there is timed with
their seconds added): a task renders its stack once with those synth effects (diffraction,
sensor exposure and noise, Bayer mosaic to DNG, ...; cached on disk), then for every noise
level adds seeded photon + read noise to the rendered values (a quick sensor model; the
``noise`` effect simulates the sensor properly;
effect sets that simulate the sensor get none on top), and for every estimator and solver
setting measures and fits. Each finished case is written as one JSON file, so an
interrupted run resumes where it stopped. Times are warm: a render's time leaves out what JAX
spent tracing and compiling its kernels (JAX's own compile events, ``without_compilation``), and
each process measures once untimed before its first timed case, so that JIT compilation
(seconds, once per process) does not pose as the price of a setting. Tasks run in a local process pool (default) or on a
Dask distributed cluster (``executor="dask"`` starts a local one; ``"dask://HOST:PORT"``
connects to a running scheduler; workers must see the output folder).

The report (``lensfit.bench.report``) turns the case files into results.json, report.md and report.html.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit.bench.suites import Suite, digest_key, render_key, render_label, scene_with_effects, solver_label
from lensfit.errors import InputError, SpecError
from lensfit.outputs.writers import write_text

_WARM: set[str] = set()  # estimators already compiled in this process


def run_group(tasks: list[dict[str, Any]], cache: str) -> list[dict[str, Any]]:
    """:func:`run_task` on tasks that differ only in their effects set (one scene, render
    setting and seed; :func:`groups`), in one process, sharing their geometric renders
    (``synth.rendering.GeometricCache``): each shot is ray-traced or convolved once for all the
    effects sets, whose images differ only in the stages after it."""
    from synth.rendering import GeometricCache

    shared = GeometricCache()
    done = []
    for task in tasks:
        done += run_task(task, cache, shared)
    return done


def costliest_first(groups_: list[list[dict[str, Any]]]) -> list[list[dict[str, Any]]]:
    """The groups in the order to hand them to parallel workers: the most samples per pixel first
    (stable), so that the last to finish are short ones and no worker waits long at the end (the
    standard suite in suite order: its last group ran 22 s alone on one of two workers)."""
    return sorted(groups_, key=lambda g: -int(g[0]["render"].get("samples_per_pixel") or 0))


def groups(tasks: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """The tasks in groups of one (scene, render setting, seed), in suite order."""
    out: dict[str, list[dict[str, Any]]] = {}
    for t in tasks:
        out.setdefault(json.dumps([t["scene"], t["render"], t["seed"]], sort_keys=True), []).append(t)
    return list(out.values())


def run_task(task: dict[str, Any], cache: str, shared=None) -> list[dict[str, Any]]:
    """Render (or reuse) the task's stack, then measure and fit every case not yet done.
    Returns the finished case records (also written to ``cache/cases/<id>.json``).
    ``shared``: a ``synth.rendering.GeometricCache`` of renders of the same shots with other effects
    (:func:`run_group`); a render that takes its geometric images from there is timed as if it
    had rendered them: the seconds they took (without compilation) are added."""
    from lensfit.bench.noise import noisy_copy, noisy_stack
    from lensfit.fitting import cramer_rao, fit
    from lensfit.runtime.jaxcache import enable_compilation_cache
    from lensfit.measurement.measure import HOLD_BYTES, measure
    from lensfit.measurement.pipeline import measure_and_fit
    from lensfit.io.stack import load_stack
    from synth.rendering import render
    from synth.stack import write_stack

    enable_compilation_cache()
    cache_dir = Path(cache)
    cases_dir = cache_dir / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    todo = [c for c in task["cases"] if _case_record(cache_dir, c["id"]) is None]
    if not todo:
        return []
    scene_path = Path(task["scene"])
    stack = cache_dir / "stacks" / render_key(task)
    fx = task.get("effects", {"name": "scene"})
    meta_path = stack / "bench_render.json"
    if not meta_path.is_file():
        if stack.exists():
            shutil.rmtree(stack)  # an interrupted render: start it again
        # Timed warm: the seconds JAX spent tracing and compiling the kernels (once per process
        # and scene structure, or loading them from the persistent cache) are left out.
        spans: list[tuple[float, float]] = []
        hits = len(shared.hits) if shared is not None else 0
        result, seconds, compiling = without_compilation(lambda: render(
            scene_with_effects(scene_path, fx), method=task["render"]["method"],
            samples_per_pixel=task["render"].get("samples_per_pixel"), seed=task["seed"],
            supersampling=task["render"].get("supersampling"), geometric_cache=shared), spans)
        shared_s = 0.0
        if shared is not None:
            for entry in shared.entries.values():  # those rendered in this call: their seconds, warm
                if "seconds" not in entry:
                    entry["seconds"] = warm_seconds(entry["window"], spans)
            shared_s = sum(shared.entries[k]["seconds"] for k in shared.hits[hits:])
        write_stack(result, stack)
        meta_path.write_text(json.dumps({"seconds": seconds + shared_s, "seconds_compiling": compiling,
                                           "seconds_geometric_shared": shared_s,
                                           "megapixels": sum(im.size for im in result.images.values()) / 1e6}))
    render_meta = json.loads(meta_path.read_text())
    truth = json.loads((stack / "truth.json").read_text())
    done = []
    by_noise: dict[str, list[dict[str, Any]]] = {}
    for c in todo:
        by_noise.setdefault(c["noise"]["name"], []).append(c)
    clean = None
    for cases in by_noise.values():
        noise = cases[0]["noise"]
        with tempfile.TemporaryDirectory(prefix="lensfit-bench-", dir=cache_dir) as tmp:
            path = stack
            if "full_well_e" in noise:
                rng = np.random.default_rng([task["seed"], int(digest_key(noise["name"]), 16) % 2**32])
                levels = (float(noise["full_well_e"]), float(noise.get("read_noise_e", 0.0)),
                          float(noise.get("exposure", 1.0)))
                # held in memory (the pixels the copy's files would hold), the clean images decoded
                # once for every noise level; written where they could not be
                if clean is None:
                    clean = load_stack(stack).holding(HOLD_BYTES)
                path = noisy_stack(clean, rng, *levels)
                if path is None:
                    path = Path(tmp) / "noisy"
                    noisy_copy(stack, path, rng, *levels)  # (nothing drawn from rng before the refusal)
            by_estimator: dict[str, Any] = {}
            for c in cases:
                record = {"id": c["id"], "scene": scene_path.stem, "render": render_label(task["render"]),
                          "render_settings": task["render"], "effects": fx["name"], "effect_settings": fx,
                          "seed": task["seed"], "noise": noise["name"],
                          "estimator": c["estimator"], "solver": solver_label(c["solver"]),
                          "seconds_render": render_meta["seconds"], "megapixels": render_meta["megapixels"]}
                try:
                    options = {"loss": c["solver"]["loss"], "blur_floor_px": c["solver"].get("blur_floor_px")}
                    if c["estimator"] not in _WARM:  # compile outside the timing, once per process
                        fit(measure(path, c["estimator"]))
                        _WARM.add(c["estimator"])
                    if c["solver"].get("diffraction_nm"):
                        # Diffraction modelled: measuring and fitting alternate (lensfit.measurement.pipeline),
                        # all of it counted as measuring.
                        t0 = time.perf_counter()
                        _, res, _ = measure_and_fit(path, c["estimator"], wavelength_nm=c["solver"]["diffraction_nm"],
                                                    fit_options=options)
                        record["seconds_fit"] = 0.0
                        record["seconds_measure"] = time.perf_counter() - t0
                    else:
                        # As `lensfit fit`: diffraction modelled where the edges show it (the test
                        # and its re-measuring counted as measuring, once per estimator), unless
                        # the solver says "off".
                        auto = c["solver"].get("diffraction", "auto") == "auto"
                        if (c["estimator"], auto) not in by_estimator:
                            t0 = time.perf_counter()
                            table = (measure_and_fit(path, c["estimator"], fit_options=options, auto_diffraction=True)[0]
                                     if auto else measure(path, c["estimator"]))
                            by_estimator[c["estimator"], auto] = (table, time.perf_counter() - t0)
                        table, t_measure = by_estimator[c["estimator"], auto]
                        t0 = time.perf_counter()
                        res = fit(table, **options)
                        record["seconds_fit"] = time.perf_counter() - t0
                        record["seconds_measure"] = t_measure
                    record.update(_compare(res, truth, cramer_rao))
                except (InputError, SpecError) as exc:  # a refusal of the input is a result too
                    record.update({"error": str(exc), "seconds_measure": None, "seconds_fit": None, "settings": {}})
                write_text(cases_dir / f"{c['id']}.json", json.dumps(record, indent=1, allow_nan=False))
                done.append(record)
    return done


#: JAX's own events for tracing, lowering and compiling (or loading compiled code from the cache).
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
_SPANS: list[tuple[float, float]] = []


def _on_span(event: str, start: float, end: float, **_: Any) -> None:
    if event in COMPILE_EVENTS:
        _SPANS.append((start, end))


def without_compilation(work: Callable[[], Any], spans_out: list | None = None) -> tuple[Any, float, float]:
    """Run ``work()``; returns (its result, seconds without JAX's compilation, seconds compiling).

    The compilation is the union of the spans JAX reports for tracing, lowering and compiling
    (``jax.monitoring`` time spans; nested ones counted once) within the call: what a second,
    warm call would not spend. Cheaper than timing a second run, which doubled the suite's
    rendering. ``spans_out``: a list that receives those spans (``time.time()`` start, end)."""
    from jax import monitoring

    monitoring.register_event_time_span_listener(_on_span)
    _SPANS.clear()
    try:
        t0, w0 = time.time(), time.perf_counter()
        out = work()
        wall, t1 = time.perf_counter() - w0, time.time()
    finally:
        monitoring.unregister_event_time_span_listener(_on_span)
    spans = sorted((max(a, t0), min(b, t1)) for a, b in _SPANS if b > t0 and a < t1)
    _SPANS.clear()
    if spans_out is not None:
        spans_out.extend(spans)
    compiling = _overlap((t0, t1), spans)
    return out, max(wall - compiling, 0.0), compiling


def _overlap(window: tuple[float, float], spans: list[tuple[float, float]]) -> float:
    """Seconds of ``window`` covered by the union of ``spans`` (sorted by start)."""
    total, reach = 0.0, window[0]
    for a, b in spans:
        a, b = max(a, reach), min(b, window[1])
        if b > a:
            total += b - a
            reach = b
    return total


def warm_seconds(window: tuple[float, float], spans: list[tuple[float, float]]) -> float:
    """The seconds of a render that ran in ``window``, less JAX's compilation within it."""
    return max(window[1] - window[0] - _overlap(window, sorted(spans)), 0.0)


def _compare(res, truth: dict[str, Any], cramer_rao: Callable) -> dict[str, Any]:
    true_f = float(truth["focal_length_mm"])
    true_settings = {k: (float(v["f_number"]), math.inf if v.get("focus_distance_mm") is None
                         else float(v["focus_distance_mm"])) for k, v in truth["settings"].items()}
    try:
        bound = cramer_rao(res, true_f, {k: true_settings[k] for k in res.settings})
    except KeyError:
        bound = {}
    out: dict[str, Any] = {"result": res.code, "reasons": res.reasons, "chi2_reduced": res.chi2_reduced,
                           "samples": res.n_samples, "settings": {}}
    for label, qs in res.settings.items():
        if label not in true_settings:
            continue
        row = {}
        for q, t in (("focal_length_mm", true_f), ("f_number", true_settings[label][0]),
                     ("focus_distance_mm", true_settings[label][1])):
            e = qs[q]
            row[q] = {"truth": t if math.isfinite(t) else None, "value": e.value, "sigma": e.sigma,
                      "ci68": list(e.ci68) if e.ci68 else None, "ci95": list(e.ci95) if e.ci95 else None,
                      "infinite": e.infinite, "crlb": bound.get(label, {}).get(q), "variance_shares": e.shares,
                      "relative_error": (e.value / t - 1) if (e.value is not None and math.isfinite(t)) else None}
        out["settings"][label] = row
    return out


# --------------------------------------------------------------------------- the suite


def run_suite(suite: Suite, out: str | Path, *, jobs: int = 1, resume: bool = False, executor: str = "local",
              progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run every case not yet done; returns all case records (old and new), in suite order.

    ``out`` must be new or empty unless ``resume`` (then finished cases are kept).
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not resume:
        raise InputError("out", str(out), "a new or empty folder", "pass --resume to continue a run there, or "
                         "choose another folder")
    cache = out / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    tasks = suite.tasks()
    total = sum(len(t["cases"]) for t in tasks)

    def finished() -> int:
        return sum(_case_record(cache, c["id"]) is not None for t in tasks for c in t["cases"])

    pending = [t for t in tasks if any(_case_record(cache, c["id"]) is None for c in t["cases"])]
    if progress:
        progress(finished(), total)
    if pending:
        if executor == "local":
            _run_local(pending, str(cache), jobs, lambda: progress(finished(), total) if progress else None)
        elif executor == "dask" or executor.startswith("dask://"):
            _run_dask(pending, str(cache), jobs, executor, lambda: progress(finished(), total) if progress else None)
        else:
            raise InputError("executor", executor, "local, dask (a local Dask cluster) or dask://HOST:PORT")
    records = []
    for t in tasks:
        for c in t["cases"]:
            if (record := _case_record(cache, c["id"])) is not None:
                records.append(record)
    return records


def _case_record(cache: Path, case_id: str) -> dict[str, Any] | None:
    """A finished case's record, or None where it is missing or is not one this suite wrote for
    that case (truncated, edited, another case's): then the case runs again and replaces it."""
    from lensfit.io.specs import load_json

    f = cache / "cases" / f"{case_id}.json"
    if not f.is_file():
        return None
    try:
        record = load_json(f, max_bytes=64 * 1024 * 1024)
    except SpecError:
        return None
    return record if isinstance(record, dict) and record.get("id") == case_id else None


def _run_local(tasks, cache: str, jobs: int, tick: Callable[[], None]) -> None:
    if jobs <= 1:
        for g in groups(tasks):
            run_group(g, cache)
            tick()
        return
    import concurrent.futures as cf
    import multiprocessing as mp

    from lensfit.runtime.running import command_process

    # spawn, not fork: JAX and OpenCV hold threads that fork does not copy safely. The workers are
    # set up as a command's process (one BLAS thread each: two workers on two cores).
    with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                initializer=command_process) as pool:
        futures = [pool.submit(run_group, g, cache) for g in costliest_first(groups(tasks))]
        for fut in cf.as_completed(futures):
            fut.result()
            tick()


def _run_dask(tasks, cache: str, jobs: int, executor: str, tick: Callable[[], None]) -> None:
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:  # pragma: no cover - dask is a dependency
        raise InputError("executor", executor, "available: install dask[distributed]") from None
    if executor == "dask":
        cluster = LocalCluster(n_workers=max(1, jobs), threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        cluster = None
        client = Client(executor.replace("dask://", "tcp://", 1))
    try:
        futures = [client.submit(run_group, g, cache, pure=False) for g in costliest_first(groups(tasks))]
        for fut in as_completed(futures):
            fut.result()
            tick()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def provenance(suite: Suite, command: list[str] | None, jobs: int, executor: str) -> dict[str, Any]:
    import platform

    from lensfit.outputs.writers import provenance as record

    out = record("lensfit", list(command) if command else [], system=platform.platform(), cores=os.cpu_count(),
                 jobs=jobs, executor=executor, suite=suite.name, suite_file=str(suite.path), seeds=list(suite.seeds))
    if not command:
        out["command"] = None
    return out
