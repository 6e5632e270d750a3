"""Benchmark of the whole chain on a rendered stack: accuracy of f, N and focus distance, and
whether the stated sigma matches the scatter over repeated noise draws.

Noise (added to a stack rendered without synth's sensor effects): each image's linear values are taken as a
fraction of a full well (``full_well_e`` electrons at 1.0), photon noise is drawn as Poisson,
read noise as Gaussian (``read_noise_e``), then clipped and quantised to 16 bits. Each draw
is seeded (``numpy.random.default_rng(seed)``); the noisy stack is written to a temporary
folder beside nothing the user owns (:func:`noisy_copy`), or, in ``lensfit bench``'s suites,
held in memory as the pixels those files would decode to (:func:`noisy_stack`).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit.bench.suites import QUANTITIES
from lensfit.fitting import fit
from lensfit.measurement.measure import measure
from lensfit.io.stack import ImageHold, Stack, load_stack


def _noisy_levels(linear: np.ndarray, rng: np.random.Generator, full_well_e: float, read_noise_e: float,
                  exposure: float) -> np.ndarray:
    """One image's noisy 16-bit levels (whole numbers 0-65535, float64): ``linear`` (full scale 1)
    times ``exposure`` as a fraction of ``full_well_e``, with photon (Poisson) and read (Gaussian)
    noise, clipped and quantised. In place on one array (five fewer passes over the image)."""
    lam = np.clip(linear, 0.0, 1.0)
    lam *= exposure
    lam *= full_well_e
    photons = rng.poisson(lam)
    value = rng.normal(0.0, read_noise_e, lam.shape)
    value += photons
    value /= full_well_e
    np.clip(value, 0.0, 1.0, out=value)
    value *= 65535
    return np.round(value, out=value)


def noisy_copy(stack_dir: Path, out: Path, rng: np.random.Generator, full_well_e: float, read_noise_e: float,
               exposure: float = 1.0) -> None:
    """A copy of a stack of linear 16-bit PNGs with photon and read noise added; ``exposure``
    scales the rendered values first (a photographer exposes below clipping at high ISO)."""
    import cv2

    stack = load_stack(stack_dir)
    out.mkdir(parents=True)
    for name in ("stack.toml", "truth.json"):
        if (stack.path / name).exists():
            shutil.copy(stack.path / name, out / name)
    for i, entry in enumerate(stack.images):
        levels = _noisy_levels(stack.read(i), rng, full_well_e, read_noise_e, exposure)
        dest = out / entry.file.relative_to(stack.path)
        dest.parent.mkdir(parents=True, exist_ok=True)
        # OpenCV's PNG writer: the same pixels as imageio's (Pillow's), written 6x faster (0.03
        # against 0.17 s per 0.96 MP image; two of every three standard-suite stacks are noisy copies)
        if not cv2.imwrite(str(dest), levels.astype(np.uint16)):
            raise OSError(f"could not write {dest}")


def noisy_stack(stack: Stack | Path, rng: np.random.Generator, full_well_e: float, read_noise_e: float,
                exposure: float = 1.0) -> Stack | None:
    """:func:`noisy_copy` held in memory: the stack (a folder, or a :class:`~lensfit.io.stack.Stack`,
    which may hold its clean images for several noise levels) holding (``Stack.hold``) the images
    that the copy's PNG files would decode to, the same to the bit (the same draws, in the same
    order, the same arithmetic), without writing and reading them back (1.2 s of a 12-image noisy
    copy was 0.5 s of PNG writing and reading). None where an image is not a plain linear PNG
    without black or white levels (whose file would decode otherwise): write the copy instead."""
    stack = stack if isinstance(stack, Stack) else load_stack(stack)
    if any(e.file.suffix.lower() != ".png" or e.encoding != "linear" or e.black_level is not None
           or e.white_level is not None for e in stack.images):
        return None
    # decoded as lensfit.io.stack reads a 16-bit PNG (levels / 65535): the levels are whole numbers,
    # which the file's uint16 keeps as they are
    hold = ImageHold(sys.maxsize)
    for i in range(len(stack.images)):
        levels = _noisy_levels(stack.read(i), rng, full_well_e, read_noise_e, exposure)
        hold.put(i, np.divide(levels, 65535.0, out=levels))
    return dataclasses.replace(stack, hold=hold)


def run(stack_dir: str | Path, *, seeds: int = 5, full_well_e: float = 20000.0, read_noise_e: float = 5.0,
        estimator: str = "edge", progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Measure and fit the stack without noise, then ``seeds`` noisy copies.

    Returns per quantity: the truth, the clean estimate's error, the noisy estimates' mean
    relative error, their standard deviation (observed scatter), the median stated sigma and
    the ratio stated/observed, plus seconds per measure and fit.
    """
    import json

    stack_dir = Path(stack_dir)
    truth = json.loads((stack_dir / "truth.json").read_text())
    label = sorted(truth["settings"])[0]
    true = {"focal_length_mm": truth["focal_length_mm"], **{q: truth["settings"][label][q] for q in QUANTITIES[1:]}}

    def one(path):
        t0 = time.perf_counter()
        table = measure(path, estimator)
        t1 = time.perf_counter()
        result = fit(table)
        t2 = time.perf_counter()
        est = result.settings[label]
        return {q: (est[q].value, est[q].sigma) for q in QUANTITIES}, t1 - t0, t2 - t1

    if progress:
        progress("clean stack")
    clean, t_measure, t_fit = one(stack_dir)
    draws = []
    with tempfile.TemporaryDirectory(prefix="lensfit-bench-") as tmp:
        for seed in range(seeds):
            if progress:
                progress(f"noise draw {seed + 1}/{seeds}")
            path = Path(tmp) / f"seed{seed}"
            noisy_copy(stack_dir, path, np.random.default_rng(seed), full_well_e, read_noise_e)
            draws.append(one(path)[0])
            shutil.rmtree(path)
    rows = []
    for q in QUANTITIES:
        values = np.array([d[q][0] if d[q][0] is not None else math.nan for d in draws])
        sigmas = np.array([d[q][1] if d[q][1] is not None else math.nan for d in draws])
        observed = float(np.nanstd(values, ddof=1)) if np.sum(np.isfinite(values)) > 1 else math.nan
        stated = float(np.nanmedian(sigmas))
        rows.append({
            "quantity": q, "truth": true[q],
            "clean_relative_error": None if clean[q][0] is None else clean[q][0] / true[q] - 1,
            "noisy_mean_relative_error": float(np.nanmean(values) / true[q] - 1),
            "noisy_max_abs_relative_error": float(np.nanmax(np.abs(values / true[q] - 1))),
            "observed_scatter": observed, "median_stated_sigma": stated,
            "stated_over_observed": stated / observed if observed > 0 else None,
            "refused": int(np.sum(~np.isfinite(values))),
        })
    return {"stack": str(stack_dir), "seeds": seeds, "full_well_e": full_well_e, "read_noise_e": read_noise_e,
            "estimator": estimator, "seconds_measure": t_measure, "seconds_fit": t_fit, "rows": rows}
