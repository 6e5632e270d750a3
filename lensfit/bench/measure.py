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
from lensfit.runtime.jaxcache import enable_compilation_cache

COC_PX = (1.0, 4.0, 16.0, 48.0)
NOISE = (0.0, 0.005, 0.02)  # standard deviation at mid grey (full scale 1)


def _render(c_px: float):
    from synth.rendering import render
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
    for k, c in enumerate(COC_PX):
        if progress:
            progress(f"slanted edges {k + 1} of {len(COC_PX)}: rendering a CoC of {c:g} px")
        image, tasks, truth = _render(c)  # edge geometry from the truth
        for name in estimators:
            fn = get_estimator(name)
            fn(image, tasks)  # warm-up (compilation)
            for noise in NOISE:
                if progress:
                    progress(f"slanted edges {k + 1} of {len(COC_PX)}: {name}, CoC {c:g} px, noise {noise:g}")
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
    return {"rows": rows, "estimators": list(estimators), "draws": draws,
            "note": "slanted-edge squares rendered by synth (raytrace/convolve auto, 256 spp); noise: "
                    "Gaussian with variance noise^2 * (value + 0.5) (shot + read), seeded"}


def run_stack(stack, estimators=("edge", "target"), progress=None) -> list[dict]:
    """Each estimator on a rendered stack with truth maps: error against the per-pixel CoC at
    each edge's middle (edges with CoC >= 1.5 px), coverage of the stated sigma, s per edge."""
    from pathlib import Path

    from scipy.ndimage import map_coordinates

    import json

    from lensfit.measurement.measure import measure

    stack = Path(stack)
    truth = json.loads((stack / "truth.json").read_text())
    maps = {i["file"]: np.load(stack / i["maps"]) for i in truth["images"]}
    rows = []
    for name in estimators:
        if progress:
            progress(f"the {name} estimator on {stack.name} against its per-pixel truth")
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
    return rows


#: Blur diameters and slants of the exact-edge bias table (:func:`run_exact`).
EXACT_COC_PX = (0.7, 1.0, 1.5, 2.0, 3.0, 6.0, 16.0, 40.0)
EXACT_SLANTS_DEG = (3.0, 8.0, 17.0, 33.0)


def exact_edge(c_px: float, slant_deg: float, offset_px: float = 0.0, supersample: int = 12,
               levels: tuple[float, float] = (0.2, 0.8)) -> tuple[np.ndarray, EdgeTask]:
    """An exact defocused edge, independent of any renderer: a half-plane (``levels`` dark and
    light) convolved with a uniform disk of diameter ``c_px``, each pixel the mean of the disk's
    edge-spread function (the fraction of the disk beyond the line, ``1/2 + (x sqrt(1 - x^2) +
    asin x) / pi`` at ``x = t / r``) over the pixel by ``supersample`` x ``supersample``
    Gauss-Legendre nodes. The edge runs ``slant_deg`` off the vertical through the image centre
    shifted ``offset_px``.

    Gauss-Legendre, not an even grid of sub-pixel centres: an n x n grid's pixel lacks
    ``1 / (12 n^2)`` px^2 of the square's variance, which reads a blur of c px low by about
    ``0.67 / (n c)^2`` (-0.46 % at 1 px with n = 12); these nodes
    hold the square's moments to the 23rd."""
    import math

    size = int(max(120, 6 * c_px + 80))
    th = math.radians(slant_deg)
    normal = np.array([math.cos(th), math.sin(th)])
    centre = (size - 1) / 2
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    nodes, weights = np.polynomial.legendre.leggauss(supersample)
    sub, weights = 0.5 * nodes, 0.5 * weights
    covered = np.zeros((size, size))
    for dy, wy in zip(sub, weights):
        for dx, wx in zip(sub, weights):
            t = (x + dx - centre - offset_px) * normal[0] + (y + dy - centre) * normal[1]
            u = np.clip(t / (c_px / 2), -1.0, 1.0)
            covered += wx * wy * (0.5 + (u * np.sqrt(1 - u * u) + np.arcsin(u)) / np.pi)
    image = levels[0] + (levels[1] - levels[0]) * covered
    along = np.array([-normal[1], normal[0]])
    mid = np.array([centre + offset_px * normal[0], centre])
    half = 0.4 * size - 4
    clear = size / 2 - 12
    return image, EdgeTask(mid - along * half, mid + along * half, clear, clear, context={})


def run_exact(noise: float = 0.005, draws: int = 40, seed: int = 0, progress=None) -> dict:
    """The edge estimator's relative bias on :func:`exact_edge` images: noise-free at every
    slant (two sub-pixel offsets each), and the mean over ``draws`` noise draws (standard
    deviation ``noise`` at mid grey, shot + read) with its standard error; beside each the
    bound the fit's error budget takes for the estimator's shared scale error
    (lensfit.fitting.constants.disk_scale_sigma: ``BLUR_SCALE_SIGMA`` and ``BLUR_SCALE_BIAS_PX2 / c^2`` in
    quadrature)."""
    from lensfit.fitting.constants import disk_scale_sigma

    enable_compilation_cache()
    fn = get_estimator("edge")
    rng = np.random.default_rng(seed)
    rows = []
    for k, c in enumerate(EXACT_COC_PX):
        if progress:
            progress(f"exact edges {k + 1} of {len(EXACT_COC_PX)}: CoC {c:g} px, {draws} noise draws")
        clean = []
        for slant in EXACT_SLANTS_DEG:
            for offset in (0.0, 0.37):
                image, task = exact_edge(c, slant, offset)
                clean.append(fn(image, [task])[0].coc_diameter_px / c - 1.0)
        image, task = exact_edge(c, 8.0, 0.2)
        noisy = []
        for _ in range(draws):
            drawn = image + rng.normal(0.0, 1.0, image.shape) * noise * np.sqrt(image + 0.5)
            r = fn(drawn, [task])[0]
            if r.coc_diameter_px is not None:
                noisy.append(r.coc_diameter_px / c - 1.0)
        noisy = np.array(noisy)
        rows.append({"coc_diameter_px": c, "bias_min": float(min(clean)), "bias_max": float(max(clean)),
                     "noisy_bias": float(noisy.mean()) if noisy.size else None,
                     "noisy_bias_se": float(noisy.std() / np.sqrt(noisy.size)) if noisy.size > 1 else None,
                     "budget": disk_scale_sigma(c)})
    return {"rows": rows, "noise": noise, "draws": draws, "slants_deg": list(EXACT_SLANTS_DEG),
            "note": "relative bias of the edge estimator on exact disk-blurred, pixel-integrated edges"}
