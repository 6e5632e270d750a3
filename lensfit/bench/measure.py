"""Blur-estimator benchmark (``lensfit bench-measure``): accuracy and time per edge.

Renders slanted-edge squares with synth (the benchmark runner may import synth; the library
does not) at several CoC diameters, adds seeded shot + read noise at several levels, runs each
estimator on the four edges with the geometry from truth.json, and reports error, bias, the
median stated sigma, the fraction of errors within it, and seconds per edge (after warm-up).
"""

from __future__ import annotations

import time

import numpy as np

from lensfit.estimators import EdgeTask, get_estimator
from lensfit.jaxcache import enable_compilation_cache

COC_PX = (1.0, 4.0, 16.0, 48.0)
NOISE = (0.0, 0.005, 0.02)  # standard deviation at mid grey (full scale 1)


def _render(c_px: float):
    from synth.render import render
    from synth.scene import scene_from_dict

    f, D, pitch, N = 50.0, 2000.0, 0.006, 2.0
    s = 1 / (1 / f - 1 / D)
    d = 1.0 / (1.0 / D - c_px * pitch / ((f / N) * s))
    R = c_px / 2
    edge_px = max(140.0, 4 * R + 60)
    size = int(edge_px + 4 * R + 80)
    mm = pitch * d / s
    scene = scene_from_dict({
        "camera": {"pixel_pitch_mm": pitch, "width_px": size, "height_px": size},
        "lens": {"focal_length_mm": f, "f_number": N, "focus_distance_mm": D},
        "render": {"samples_per_pixel": 256},
        "background": {"value": 0.5},
        "object": [{"id": "edge", "target": "slanted-edge", "distance_mm": d, "angle_deg": 5.0,
                    "edge_mm": edge_px * mm, "size_mm": [size * mm * 1.2] * 2}],
    })
    result = render(scene)
    target = result.truth["images"][0]["targets"][0]
    clear = 0.5 * edge_px
    tasks = [EdgeTask(np.array(e["start_px"]), np.array(e["end_px"]), clear, clear,
                      context={}) for e in target["edges"]]
    truth = np.array([e["coc_diameter_px"][1] for e in target["edges"]])
    return next(iter(result.images.values())).astype(np.float64), tasks, truth


def run(draws: int = 3, seed: int = 0, estimators=("edge",), progress=None) -> dict:
    """Rows of (estimator, coc, noise): rms error, bias, median sigma, coverage, s per edge.

    Only estimators that need no target pose apply to these bare edges (``edge``); the
    ``target`` estimator is compared on a whole stack by :func:`run_stack`.
    """
    enable_compilation_cache()
    rng = np.random.default_rng(seed)
    rows = []
    for c in COC_PX:
        image, tasks, truth = _render(c)  # edge geometry from the truth
        for name in estimators:
            fn = get_estimator(name)
            fn(image, tasks)  # warm-up (compilation)
            for noise in NOISE:
                errs, sigmas, seconds = [], [], 0.0
                for _ in range(draws):
                    var = noise**2 * (image + 0.5)  # shot + read: noise**2 at mid grey
                    noisy = image + rng.normal(0.0, 1.0, image.shape) * np.sqrt(var) if noise else image
                    t = time.perf_counter()
                    res = fn(noisy, tasks)
                    seconds += time.perf_counter() - t
                    for r, tv in zip(res, truth):
                        if r.coc_diameter_px is not None:
                            errs.append(r.coc_diameter_px - tv)
                            sigmas.append(r.sigma_px)
                errs, sigmas = np.array(errs), np.array(sigmas)
                rows.append({"estimator": name, "coc_diameter_px": c, "noise": noise, "edges": int(errs.size),
                             "rms_error_px": float(np.sqrt(np.mean(errs**2))) if errs.size else None,
                             "bias_px": float(errs.mean()) if errs.size else None,
                             "median_sigma_px": float(np.median(sigmas)) if errs.size else None,
                             "within_1_sigma": float(np.mean(np.abs(errs) <= sigmas)) if errs.size else None,
                             "seconds_per_edge": seconds / max(draws * len(tasks), 1)})
                if progress:
                    progress(f"{name} c={c:g} noise={noise:g}")
    return {"rows": rows, "estimators": list(estimators), "draws": draws,
            "note": "slanted-edge squares rendered by synth (raytrace/convolve auto, 256 spp); noise: "
                    "Gaussian with variance noise^2 * (value + 0.5) (shot + read), seeded"}


def run_stack(stack, estimators=("edge", "target"), progress=None) -> list[dict]:
    """Each estimator on a rendered stack with truth maps: error against the per-pixel CoC at
    each edge's middle (edges with CoC >= 1.5 px), coverage of the stated sigma, s per edge."""
    from pathlib import Path

    from scipy.ndimage import map_coordinates

    import json

    from lensfit.measure import measure

    stack = Path(stack)
    truth = json.loads((stack / "truth.json").read_text())
    maps = {i["file"]: np.load(stack / i["maps"]) for i in truth["images"]}
    rows = []
    for name in estimators:
        t = time.perf_counter()
        table = measure(stack, name)
        seconds = time.perf_counter() - t
        errs, sigmas = [], []
        for smp in table.valid():
            mid = (np.array(smp.start_px) + np.array(smp.end_px)) / 2
            c = map_coordinates(maps[smp.image]["coc_diameter_px"], [[mid[1]], [mid[0]]], order=1)[0]
            if c >= 1.5:
                errs.append(smp.coc_diameter_px - c)
                sigmas.append(smp.sigma_px)
        errs, sigmas = np.array(errs), np.array(sigmas)
        rows.append({"estimator": name, "edges": len(table), "compared": int(errs.size),
                     "rms_error_px": float(np.sqrt(np.mean(errs**2))), "median_abs_error_px": float(np.median(np.abs(errs))),
                     "bias_px": float(errs.mean()), "within_1_sigma": float(np.mean(np.abs(errs) <= sigmas)),
                     "seconds_total": seconds, "seconds_per_edge": seconds / max(len(table), 1)})
        if progress:
            progress(f"{name} on {stack.name}")
    return rows
