"""Where a fit's time goes (``lensfit bench-stages``): seconds per stage, cold and warm, against
image count and megapixels, and the whole ``lensfit fit`` against OpenCV's own detect+calibrate.

Stages (``SampleTable.stage_seconds`` and ``FitResult.stage_seconds``): read (decode and
linearise), detect (targets), calibrate (intrinsics, poses, edge geometry), measure (the blur
of every edge), fit (the solver), uncertainty (covariance, jackknife, every reported quantity).

Each configuration runs in a fresh process (``cold``: imports, loading the stored traces and
compiled code of ``lensfit.runtime.jaxcache`` / the persistent cache) and again ``warm_runs`` times in that
process (``warm``: each stage's median over them; one warm call alone scatters by a fifth).
Sizes: the first k images of the stack, and the whole stack enlarged by a factor (bilinear, the
pixel pitch divided by it: the same scene at more pixels). The OpenCV reference reads the same
files, detects the ChArUco board and calibrates (cv2.aruco + cv2.calibrateCamera, nothing of
lensfit) in a fresh process; its ratio to a whole ``lensfit fit`` is the figure of merit.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

STAGES = ("read", "detect", "calibrate", "measure", "fit", "uncertainty")

_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
from lensfit.runtime.jaxcache import enable_compilation_cache
enable_compilation_cache()
from lensfit.measurement.measure import measure
from lensfit.fitting import fit
out = {}
warm = []
for k in range(1 + int(sys.argv[2])):
    t = time.perf_counter()
    table = measure(sys.argv[1])
    result = fit(table)
    secs = {**table.stage_seconds, **result.stage_seconds}
    secs["total"] = time.perf_counter() - t
    if k == 0:
        out["cold"], out["cold_edges"] = secs, len(table)
    else:
        warm.append(secs)
out["warm_runs"] = warm
out["process_start"] = t0
print(json.dumps(out))
"""

_OPENCV = r"""
import sys, time, tomllib
from pathlib import Path
import cv2, numpy as np
folder = Path(sys.argv[1])
spec = tomllib.loads((folder / "stack.toml").read_text())
detectors = []
for t in spec["target"]:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, t["dictionary"]))
    board = cv2.aruco.CharucoBoard(tuple(t["squares"]), t["square_mm"], t["marker_mm"], d)
    board.setLegacyPattern(bool(t.get("legacy_pattern", False)))
    detectors.append((board, cv2.aruco.CharucoDetector(board)))
obj, img, size = [], [], None
for entry in spec["image"]:
    im = cv2.imread(str(folder / entry["file"]), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if im.dtype != np.uint8:  # linear 16-bit: a display gamma for the detector
        im = (255.0 * np.sqrt(im / max(float(im.max()), 1.0))).astype(np.uint8)
    size = im.shape[::-1]
    for board, det in detectors:
        corners, ids, _, _ = det.detectBoard(im)
        if ids is not None and len(ids) >= 6:
            o, i = board.matchImagePoints(corners, ids)
            obj.append(o); img.append(i)
rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None)
print(len(obj), K[0, 0])
"""


def _python() -> str:
    return sys.executable


def _run(code: str, *args: str, env: dict | None = None) -> tuple[float, str]:
    t = time.perf_counter()
    out = subprocess.run([_python(), "-c", code, *args], capture_output=True, text=True, env=env, check=True)
    return time.perf_counter() - t, out.stdout


def _same_numpy_env() -> dict[str, str]:
    """The environment of the OpenCV reference: numpy's memory settings as the ``lensfit``
    process sets its own (``lensfit.runtime.running.NUMPY_ENV``), so that the ratio compares the work,
    not the kernel's handling of huge pages (the reference's float64 temporaries stall the same)."""
    from lensfit.runtime.running import NUMPY_ENV

    return {**NUMPY_ENV, **os.environ}


def _run_measured(*argv: str) -> tuple[float, float, float]:
    """Seconds, peak resident memory (MiB, the process's own) and CPU seconds of ``python -m
    lensfit ARGV``."""
    from lensfit.bench.peak import run_with_peak

    ran = run_with_peak([_python(), "-m", "lensfit", *argv], timeout_s=24 * 3600)
    if ran.status != 0:
        raise subprocess.CalledProcessError(ran.status if ran.status is not None else -1, argv, "", ran.stderr)
    return ran.seconds, ran.peak_bytes / 2**20, ran.cpu_seconds


def subset(src: Path, dst: Path, count: int | None, scale: float) -> Path:
    """A copy of the stack with its first ``count`` images (more than it has: its images again,
    in turn, under new names), enlarged ``scale`` times."""
    import cv2
    import tomli_w

    spec = tomllib.loads((src / "stack.toml").read_text())
    images = spec["image"]
    count = count or len(images)
    chosen = []
    for k in range(count):
        entry = dict(images[k % len(images)])
        if k >= len(images):  # a repeat: the same photograph under another name
            stem, dot, suffix = entry["file"].rpartition(".")
            entry["file"] = f"{stem}_again{k // len(images)}{dot}{suffix}"
        chosen.append((images[k % len(images)]["file"], entry))
    dst.mkdir(parents=True)
    for original, entry in chosen:
        (dst / entry["file"]).parent.mkdir(parents=True, exist_ok=True)
        if scale == 1.0:
            (dst / entry["file"]).write_bytes((src / original).read_bytes())
        else:
            im = cv2.imread(str(src / original), cv2.IMREAD_UNCHANGED)
            big = cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
            cv2.imwrite(str(dst / entry["file"]), big)
    images = [entry for _, entry in chosen]
    spec["image"] = images
    camera = spec.get("camera", {})
    if scale != 1.0:
        for key in ("pixel_pitch_mm",):
            if key in camera:
                camera[key] = camera[key] / scale
        for key in ("width_px", "height_px"):
            if key in camera:
                camera[key] = int(round(camera[key] * scale))
        spec.pop("intrinsics", None)
    (dst / "stack.toml").write_text(tomli_w.dumps(spec))
    return dst


def run(stack: str | Path, counts: tuple[int, ...] = (3, 6, 12), scales: tuple[float, ...] = (1.0, 1.5, 2.0),
        progress=None, repeat: int = 3, warm_runs: int = 3, jobs: tuple[int, ...] = (1,),
        shots: tuple[int, ...] = ()) -> dict:
    """Rows of seconds per stage (cold and warm) per configuration; the OpenCV ratio per scale.

    Returns {"rows": [...], "provenance": ...}; each row: images, megapixels, edges, cold and warm
    seconds per stage and in total (warm: the median of ``warm_runs`` calls), the whole-process
    seconds of ``lensfit fit`` and of the OpenCV reference, and their ratio (scales only):
    ``repeat`` pairs of the two processes run back to back (a virtual machine's speed drifts
    within minutes), the median of each and of the pairs' ratios (``ratios``: every pair's).
    With more than one count in ``jobs``, the whole ``lensfit fit`` runs at each ``--jobs`` too
    (``lensfit_fit_process_s_by_jobs``, the medians of ``repeat`` runs taken in turn), the speed-up
    of the most over one (``jobs_speedup``) and whether every run's results were the same
    (``jobs_identical``, provenance aside); the ratio to OpenCV is then the most jobs' run.
    ``shots``: whole-stack rows of each of these many images at every scale (the stack's own
    again, in turn, where it has fewer; default: the stack's own count); each whole ``lensfit
    fit`` process's peak resident memory is in ``lensfit_fit_peak_mib`` (the largest over its
    runs), and the cores it kept busy (CPU seconds over wall seconds) in
    ``lensfit_fit_cores_busy_by_jobs``."""
    from lensfit.outputs.writers import provenance

    stack = Path(stack)
    wholes = sorted(set(shots)) or [len(tomllib.loads((stack / "stack.toml").read_text())["image"])]
    # (images, scale, whether the whole-process comparison runs on it)
    configs = [(c, 1.0, False) for c in counts if c < wholes[0]] + [(n, s, True) for s in scales for n in wholes]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (count, scale, whole) in enumerate(configs):
            if progress:
                progress(f"{count} images x{scale:g}", k, len(configs))
            folder = subset(stack, Path(tmp) / f"s{k}", count, scale)
            _, out = _run(_CHILD, str(folder), str(max(warm_runs, 1)))
            child = json.loads(out.strip().splitlines()[-1])
            h, w = _shape(folder)
            row = {"images": count, "megapixels": round(h * w / 1e6, 3), "edges": child["cold_edges"],
                   "cold": {s: child["cold"].get(s, 0.0) for s in (*STAGES, "total")},
                   "warm": {s: statistics.median(r.get(s, 0.0) for r in child["warm_runs"])
                            for s in (*STAGES, "total")},
                   "warm_runs": len(child["warm_runs"])}
            if whole:  # whole process: lensfit fit against OpenCV's detect + calibrate
                pairs, by_jobs, documents, peak = [], {n: [] for n in jobs}, [], 0.0
                busy: dict[int, list[float]] = {n: [] for n in jobs}
                for j in range(max(repeat, 1)):
                    for n in jobs:
                        out_json = Path(tmp) / f"r{k}-{j}-{n}.json"
                        t_fit, mib, cpu = _run_measured("fit", str(folder), "--out", str(out_json), "--jobs", str(n))
                        peak = max(peak, mib)
                        busy[n].append(cpu / t_fit)
                        by_jobs[n].append(t_fit)
                        document = json.loads(out_json.read_text())
                        document.pop("provenance", None)
                        documents.append(document)
                    t_cv, _ = _run(_OPENCV, str(folder), env=_same_numpy_env())
                    pairs.append((by_jobs[jobs[-1]][-1], t_cv))
                fits, cvs = zip(*pairs)
                row.update(lensfit_fit_process_s=statistics.median(fits), opencv_process_s=statistics.median(cvs),
                           ratio=statistics.median(f / c for f, c in pairs), ratios=[f / c for f, c in pairs],
                           lensfit_fit_peak_mib=peak)
                if len(jobs) > 1:
                    medians = {n: statistics.median(v) for n, v in by_jobs.items()}
                    row.update(lensfit_fit_process_s_by_jobs=medians,
                               lensfit_fit_cores_busy_by_jobs={n: statistics.median(v) for n, v in busy.items()},
                               jobs_speedup=medians[jobs[0]] / medians[jobs[-1]],
                               jobs_identical=all(d == documents[0] for d in documents))
            rows.append(row)
    if progress:
        progress("done", len(configs), len(configs))
    return {"rows": rows, "jobs": list(jobs), "provenance": provenance("lensfit bench-stages", cores=os.cpu_count())}


def _shape(folder: Path) -> tuple[int, int]:
    from lensfit.io.images import image_size

    spec = tomllib.loads((folder / "stack.toml").read_text())
    w, h = image_size(folder / spec["image"][0]["file"])
    return h, w


def table(report: dict) -> str:
    """The rows as a Markdown table (seconds; cold / warm)."""
    head = ("| images | MP | edges | " + " | ".join(STAGES) + " | total | `lensfit fit` process | its peak memory "
            "| OpenCV detect+calibrate | ratio |")
    lines = [head, "|" + "---|" * (len(STAGES) + 8)]
    for r in report["rows"]:
        cells = [f"{r['cold'][s]:.2f} / {r['warm'][s]:.2f}" for s in (*STAGES, "total")]
        extra = ([f"{r['lensfit_fit_process_s']:.1f} s", f"{r['lensfit_fit_peak_mib']:.0f} MiB",
                  f"{r['opencv_process_s']:.1f} s", f"{r['ratio']:.1f}x"] if "ratio" in r else ["", "", "", ""])
        lines.append(f"| {r['images']} | {r['megapixels']:.2f} | {r['edges']} | " + " | ".join(cells + extra) + " |")
    jobs = report.get("jobs") or [1]
    if len(jobs) > 1:
        lines += ["", "| images | MP | " + " | ".join(f"`--jobs {n}`" for n in jobs) + " | speed-up | results |"
                  " cores busy (CPU seconds over wall seconds) |", "|" + "---|" * (len(jobs) + 5)]
        for r in report["rows"]:
            if "jobs_speedup" in r:
                by_jobs = {int(k): v for k, v in r["lensfit_fit_process_s_by_jobs"].items()}  # (JSON keys are text)
                times = " | ".join(f"{by_jobs[n]:.1f} s" for n in jobs)
                same = "identical" if r["jobs_identical"] else "DIFFER"
                cores = {int(k): v for k, v in r.get("lensfit_fit_cores_busy_by_jobs", {}).items()}
                busy = " / ".join(f"{cores[n]:.2f}" for n in jobs if n in cores)
                lines.append(f"| {r['images']} | {r['megapixels']:.2f} | {times} | {r['jobs_speedup']:.2f}x | {same} | "
                             f"{busy} |")
    return "\n".join(lines)


def markdown(report: dict) -> str:
    """The record as the validation page's section: where the time and memory of a fit go."""
    prov = report.get("provenance") or {}
    return "\n".join([
        "### Where a fit's time and memory go (`lensfit bench-stages`)", "",
        f"`{prov.get('command') or prov.get('program')}`, {str(prov.get('date', ''))[:10]}, "
        f"{prov.get('cores')} cores. Seconds cold / warm per stage in one process; the whole `lensfit fit` "
        "process (its peak memory its own) against OpenCV's read + ChArUco detection + calibration of the same "
        "files. Larger stacks are the demo's photographs enlarged (bilinear) and taken again under new names.", "",
        table(report)])
