"""Renderer speed figures (``synth bench``): what accuracy costs in time.

Measured, never asserted in tests. Each figure is the best of ``repeats`` runs after a warm-up
call (compilation excluded); compilation is reported separately, cold and from JAX's
persistent cache in a fresh process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lensfit.io.specs import specs_dir


def _best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _compile_times(scene_path: Path, shot_index: int) -> dict[str, float]:
    """Seconds of the first raytrace call in a fresh process: cold cache, then warm cache."""
    code = (
        "import sys, time\n"
        "from lensfit.runtime.jaxcache import enable_compilation_cache\n"
        "enable_compilation_cache()\n"
        "from synth.scene import load_scene\n"
        "from synth.raytrace import render_raytrace\n"
        f"shot = load_scene({str(scene_path)!r}).shots[{shot_index}]\n"
        "t = time.perf_counter(); render_raytrace(shot, 0.3, 64, 0); first = time.perf_counter() - t\n"
        "t = time.perf_counter(); render_raytrace(shot, 0.3, 64, 0); second = time.perf_counter() - t\n"
        "print(first - second)\n"
    )
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "LENSFIT_JAX_CACHE": cache}
        for label in ("compile_cold_s", "compile_cached_s"):
            proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            out[label] = max(0.0, float(proc.stdout.strip().splitlines()[-1]))
    return out


def run_bench(repeats: int = 3, spp_list=(4, 16, 64, 256, 1024), include_compile: bool = True,
              progress=None) -> dict:
    """Measure the renderer on the demo scene.

    Returns
    -------
    dict with ``raytrace`` rows (spp, seconds per 1-MP shot with every pixel traced, million lens
    samples per second, seconds with the constant regions taken without samples, RMS error
    against a converged reference), the fraction of each shot's pixels traced, ``convolve`` rows
    (supersampling, seconds, RMS error against the same reference), compile times and the
    machine description.
    """
    from synth.convolve import render_convolve
    from synth.flat import constant_pixels
    from synth.raytrace import camera_array, render_raytrace, scene_arrays
    from synth.scene import load_scene

    path = specs_dir() / "scenes" / "demo.toml"
    scene = load_scene(path)
    # A fronto-parallel shot (both methods exact) and a tilted one (ray tracing only).
    flat_index = next(i for i, s in enumerate(scene.shots) if all(o.pose.fronto_parallel for o in s.objects))
    tilted_index = next(i for i, s in enumerate(scene.shots) if not all(o.pose.fronto_parallel for o in s.objects))
    flat, tilted = scene.shots[flat_index], scene.shots[tilted_index]
    bg = scene.background_value
    pixels = flat.camera.width_px * flat.camera.height_px

    def step(msg):
        if progress is not None:
            progress(msg)

    # Reference: convolve with exact area sampling at 8 x 8 sub-pixels, which agrees with
    # 4096-spp ray tracing to within the ray tracer's noise (tests/synth/test_synth_render.py).
    step("reference (convolve, 8 x 8 sub-pixels)")
    reference = render_convolve(flat, bg, 8).astype(np.float64)
    rows_rt = []
    traced = {}
    for name, shot in (("flat", flat), ("tilted", tilted)):
        cam = shot.camera
        known = constant_pixels(*scene_arrays(shot), camera_array(cam), cam.width_px, cam.height_px, bg)
        traced[name] = float(np.isnan(known).mean())
    for spp in spp_list:
        step(f"raytrace {spp} spp")
        # The kernel's speed with every pixel traced; then as a render runs, with the pixels of
        # constant regions taken without samples (synth.flat), the same image.
        render_raytrace(flat, bg, spp, 0)  # compile
        seconds = _best(lambda: render_raytrace(flat, bg, spp, 1, constant_regions=False), repeats)
        err = float(np.sqrt(np.mean((render_raytrace(flat, bg, spp, 2) - reference) ** 2)))
        tilted_s = _best(lambda: render_raytrace(tilted, bg, spp, 1, constant_regions=False), repeats)
        rows_rt.append({"samples_per_pixel": spp, "seconds": seconds, "seconds_tilted_charuco": tilted_s,
                        "mega_lens_samples_per_s": pixels * spp / seconds / 1e6,
                        "seconds_constant_regions": _best(lambda: render_raytrace(flat, bg, spp, 1), repeats),
                        "seconds_tilted_constant_regions": _best(lambda: render_raytrace(tilted, bg, spp, 1), repeats),
                        "rms_error": err})
    rows_cv = []
    for ss in (1, 2, 4):
        step(f"convolve {ss} x {ss}")
        render_convolve(flat, bg, ss)
        seconds = _best(lambda: render_convolve(flat, bg, ss), repeats)
        err = float(np.sqrt(np.mean((render_convolve(flat, bg, ss) - reference) ** 2)))
        rows_cv.append({"supersampling": ss, "seconds": seconds, "rms_error": err})
    result = {
        "scene": str(path.name), "flat_shot": flat.name, "tilted_shot": tilted.name,
        "image_px": [flat.camera.width_px, flat.camera.height_px],
        "coc_diameter_px_flat": float(flat.camera.coc_diameter_px(flat.objects[0].pose.t_cam_target[2])),
        "raytrace": rows_rt, "convolve": rows_cv, "traced_fraction": traced,
        "machine": {"cores": os.cpu_count(), "python": sys.version.split()[0]},
        "error_note": "RMS error of linear intensity (full scale 1) against convolve at 8 x 8 sub-pixels",
    }
    if include_compile:
        step("compile time, cold and cached (fresh processes)")
        result.update(_compile_times(path, tilted_index))
    return result


#: The Mitsuba side of :func:`against_mitsuba`: a process that imports Mitsuba (and numpy, and
#: the few lines of synth.mitsuba that build its scene from plain data: none of synth's renderer,
#: no JAX), renders each described shot and writes it as Mitsuba's own EXR.
_MITSUBA_PROCESS = """
import os, pickle, sys
from synth.mitsuba import build_scene, load_mitsuba
mi = load_mitsuba(sys.argv[2])
with open(sys.argv[1], "rb") as fh:
    shots = pickle.load(fh)
for k, desc in enumerate(shots):
    image = mi.render(mi.load_dict(build_scene(mi, desc)))
    mi.Bitmap(image).write(os.path.join(sys.argv[3], f"shot_{k:03d}.exr"))
"""


def against_mitsuba(scene_path: str | Path | None = None, samples_per_pixel: int = 32, pairs: int = 3,
                    variant: str = "llvm_ad_rgb", progress=None) -> dict:
    """Whole processes, synth's ray tracer against Mitsuba 3 on the same scene and samples per
    pixel: ``pairs`` times, back to back, ``synth render SCENE --method raytrace --spp S`` (start-up,
    JAX's import, loading or compiling the tracer, rendering, writing 16-bit PNGs, truth maps and
    truth.json) and a process that imports Mitsuba, builds each shot's scene (``thinlens``
    camera, box pixel filter, ``independent`` sampler: ``synth.mitsuba``), renders it and writes
    an EXR (``variant``: ``llvm_ad_rgb``, Dr.Jit's vectorised LLVM backend, or ``scalar_rgb``).
    Returns both sides' seconds per run, medians, million lens samples per second and the
    median of the pairs' ratios (Mitsuba's seconds over synth's)."""
    import pickle

    from synth.mitsuba import check, describe
    from synth.scene import load_scene
    from synth.seeds import raytrace_seed

    path = Path(scene_path) if scene_path is not None else specs_dir() / "scenes" / "demo.toml"
    scene = load_scene(path)
    for shot in scene.shots:
        check(shot, scene.effects)
    shots = [describe(shot, scene.background_value, samples_per_pixel, raytrace_seed(scene.render.seed, k))
             for k, shot in enumerate(scene.shots)]
    samples = sum(s["width_px"] * s["height_px"] for s in shots) * samples_per_pixel
    synth_s, mitsuba_s = [], []
    with tempfile.TemporaryDirectory() as tmp:
        job = Path(tmp) / "shots.pkl"
        job.write_bytes(pickle.dumps(shots))
        for i in range(pairs):
            for label, argv, times in (
                    ("synth", [sys.executable, "-m", "synth.cli", "render", str(path), "--method", "raytrace",
                               "--spp", str(samples_per_pixel), "--out", str(Path(tmp) / f"synth{i}")], synth_s),
                    ("mitsuba", [sys.executable, "-c", _MITSUBA_PROCESS, str(job), variant,
                                 str(Path(tmp) / f"mitsuba{i}")], mitsuba_s)):
                if progress is not None:
                    progress(f"pair {i + 1}/{pairs}: {label}")
                if label == "mitsuba":
                    (Path(tmp) / f"mitsuba{i}").mkdir()
                t = time.perf_counter()
                proc = subprocess.run(argv, cwd=tmp, capture_output=True, text=True)
                times.append(time.perf_counter() - t)
                if proc.returncode != 0:
                    raise RuntimeError(f"{label} process failed: {(proc.stderr or proc.stdout).strip()[-400:]}")
    synth_med, mitsuba_med = float(np.median(synth_s)), float(np.median(mitsuba_s))
    return {"scene": path.name, "shots": len(shots), "samples_per_pixel": samples_per_pixel,
            "lens_samples": samples, "mitsuba_variant": variant, "synth_s": synth_s, "mitsuba_s": mitsuba_s,
            "synth_median_s": synth_med, "mitsuba_median_s": mitsuba_med,
            "synth_mega_samples_per_s": samples / synth_med / 1e6,
            "mitsuba_mega_samples_per_s": samples / mitsuba_med / 1e6,
            "ratio": float(np.median([m / s for s, m in zip(synth_s, mitsuba_s)])),
            "machine": {"cores": os.cpu_count(), "python": sys.version.split()[0]}}


#: Designs whose cost per lens sample the record sets beside the thin lens's: (what, prescription).
COMPOUND_DESIGNS = (("Cooke triplet, 6 surfaces", "cooke-triplet-50"), ("telephoto, 7 surfaces", "telephoto-250"),
                    ("double Gauss, 11 surfaces", "double-gauss-50"), ("retrofocus, 13 surfaces", "retrofocus-24"))


def lens_sample_costs(samples_per_pixel: int = 16, repeats: int = 3, progress=None) -> list[dict]:
    """Nanoseconds per lens sample of the ray tracer's kernel (warm, every pixel traced, the best
    of ``repeats``) through the thin lens (the demo scene's first shot) and through each of
    ``COMPOUND_DESIGNS`` (the compound-lens scene's first shot with that prescription), at
    ``samples_per_pixel``, one wavelength."""
    from synth.plan_costs import scene_with
    from synth.raytrace import render_raytrace
    from synth.scene import load_scene

    cases = [("thin lens", load_scene(specs_dir() / "scenes" / "demo.toml"))]
    cases += [(what, scene_with("compound_lens.toml", {"lens.prescription": name})) for what, name in COMPOUND_DESIGNS]
    rows = []
    for what, scene in cases:
        if progress is not None:
            progress(f"lens samples: {what}")
        shot = scene.shots[0]
        bg = scene.background_value
        render_raytrace(shot, bg, samples_per_pixel, 0, constant_regions=False)  # compilation
        seconds = _best(lambda: render_raytrace(shot, bg, samples_per_pixel, 1, constant_regions=False), repeats)
        samples = shot.camera.width_px * shot.camera.height_px * samples_per_pixel
        rows.append({"lens": what, "surfaces": 0 if shot.camera.prescription is None else
                     len(shot.camera.prescription.surfaces), "image_px": [shot.camera.width_px, shot.camera.height_px],
                     "samples_per_pixel": samples_per_pixel, "seconds": seconds,
                     "ns_per_lens_sample": 1e9 * seconds / samples})
    thin = rows[0]["ns_per_lens_sample"]
    for r in rows:
        r["cost_over_thin_lens"] = r["ns_per_lens_sample"] / thin
    return rows


def mitsuba_record(rows: list[dict], pairs: int, progress=None, folder: str = "docs/validation/records") -> dict:
    """The record ``synth bench --against-mitsuba --record``: ``rows``, :func:`against_mitsuba`'s
    results on the demo scene (one per samples-per-pixel), and the kernel's cost per lens sample,
    thin lens beside compound ones (:func:`lens_sample_costs`); ``folder``: where it is written (its
    command names it)."""
    from lensfit.bench.records import record_header

    spp = " ".join(str(r["samples_per_pixel"]) for r in rows)
    return {**record_header("synth_vs_mitsuba",
                            f"synth bench --against-mitsuba --spp {spp} --pairs {pairs} --record {folder}"),
            "rows": rows, "lens_samples": lens_sample_costs(progress=progress)}


def markdown(doc: dict) -> str:
    """The record as the validation page's section."""
    out = ["### synth against Mitsuba 3 (`synth bench --against-mitsuba`)", "",
           f"`{doc['command']}`, {doc['date']}, {doc['system']}, {doc['cores']} cores. Whole processes on the demo "
           "scene (12 shots of 1200 x 800 px), back to back: `synth render --method raytrace` (start-up, JAX, the "
           "stored tracer, rendering, 16-bit PNGs, truth maps) against a process that imports Mitsuba 3, builds "
           "each shot's scene (thin-lens camera, box filter, independent sampler), renders it and writes an EXR. "
           "synth takes pixels whose every ray meets one uniform region at that region's value without "
           "sampling them (exact); the rest get the samples asked for.", "",
           "| samples per pixel | synth s (median) | Mitsuba s (median) | synth's time over Mitsuba's |",
           "|---|---|---|---|"]
    for r in doc["rows"]:
        out.append(f"| {r['samples_per_pixel']} | {r['synth_median_s']:.2f} | {r['mitsuba_median_s']:.2f} "
                   f"({r['mitsuba_variant']}) | {r['synth_median_s'] / r['mitsuba_median_s']:.2f}x |")
    out += ["", "The tracer's kernel alone (warm, every pixel traced, one wavelength): its cost per lens sample "
            "through the thin lens and through compound designs, each ray traced through every surface.", "",
            "| lens | surfaces | ns per lens sample | over the thin lens |", "|---|---|---|---|"]
    for r in doc["lens_samples"]:
        out.append(f"| {r['lens']} | {r['surfaces']} | {r['ns_per_lens_sample']:.1f} | "
                   f"{r['cost_over_thin_lens']:.1f}x |")
    return "\n".join(out)


def record(doc: dict, folder: str | Path) -> Path:
    """Write the record ``folder/synth_vs_mitsuba.json``."""
    from lensfit.bench.records import write_json

    return write_json(folder, "synth_vs_mitsuba", doc)


if __name__ == "__main__":  # python -m synth.bench
    print(json.dumps(run_bench(), indent=1))
