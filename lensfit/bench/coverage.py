"""Coverage of a benchmark's intervals and how honest they are: the share holding the truth with
its binomial (Wilson) interval over the effective number of intervals (those drawn on one render
share its errors: :func:`design_effect`), and beyond coverage the error over sigma, the half-width
over the error, the reliability curve and the tails (:func:`interval_honesty`).
``lensfit.bench.report`` puts them in results.json, the tables and the plots."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lensfit.bench.suites import QUANTITIES


def wilson_interval(hits: int, n: int, z: float = 1.959963984540054) -> list[float]:
    """95 % Wilson score interval of a coverage ``hits / n`` (a binomial proportion): how well a
    benchmark of ``n`` intervals can tell 95 % coverage from 85 % (e.g. 40 intervals all holding
    the truth: 91-100 %)."""
    p = min(max(hits / n, 0.0), 1.0)
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # exact at the ends (every or no interval holding the truth: 1 or 0), where rounding of an
    # effective count's hits (coverage_summary) would leave the bound a hair inside
    return [0.0 if p <= 1e-12 else max(0.0, centre - half), 1.0 if p >= 1 - 1e-12 else min(1.0, centre + half)]


def design_effect(groups: list[list[float]]) -> tuple[float, float]:
    """(intracluster correlation, design effect) of values in ``groups``: the one-way ANOVA
    estimator of the correlation ``rho`` between two values of one group (clipped to [0, 1];
    unequal group sizes through the usual ``m0``), and ``1 + (m - 1) rho``, ``m`` the mean group
    size: by how much the groups' correlation inflates the variance of a mean of all the values
    (Kish). With fewer than 3 groups the correlation cannot be estimated and is taken as 1 (each
    group counts once)."""
    groups = [list(g) for g in groups if len(g)]
    n, k = sum(map(len, groups)), len(groups)
    if k < 3 or n <= k:
        return 1.0, float(n) / max(k, 1)
    mean = sum(map(sum, groups)) / n
    msb = sum(len(g) * (float(np.mean(g)) - mean) ** 2 for g in groups) / (k - 1)
    msw = sum(float(np.sum((np.asarray(g) - np.mean(g)) ** 2)) for g in groups) / (n - k)
    m0 = (n - sum(len(g) ** 2 for g in groups) / n) / (k - 1)
    rho = 1.0 if msb + (m0 - 1.0) * msw <= 0 else (msb - msw) / (msb + (m0 - 1.0) * msw)
    rho = min(max(rho, 0.0), 1.0)
    return rho, 1.0 + (n / k - 1.0) * rho


def coverage_summary(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per quantity: the share of 68 % and 95 % intervals holding the truth, with a 95 % interval
    of that share that counts what the intervals share. Intervals from one geometric render (one
    scene, render setting and seed: the effect sets, noise levels and solver settings of a case
    draw on the same rendered light, and a bench fit's settings on one calibration) are not
    independent: the Wilson interval is taken over the effective number of intervals, their
    count over the design effect (:func:`design_effect`) of their errors in units of their sigma,
    ``(value - truth) / sigma``, grouped by render. That correlation is an upper bound on the one
    of the hit-or-miss indicators (a threshold loses correlation), so the interval errs wide;
    ``coverage95_ci95_if_independent`` keeps the one that takes every interval as independent
    (the standard suite's 378 focal-length intervals count as about 25 there)."""
    coverage = {}
    for q in QUANTITIES:
        mine = [x for x in rows if x["quantity"] == q]
        groups: dict[tuple, list[float]] = {}
        for x in mine:
            if x["value"] is not None and x["truth"] is not None and x["sigma"]:
                key = (x["scene"], x["render"], x["seed"])
                groups.setdefault(key, []).append((x["value"] - x["truth"]) / x["sigma"])
        rho, deff = design_effect(list(groups.values()))
        entry: dict[str, Any] = {"clusters": len(groups), "intracluster_correlation": rho, "design_effect": deff}
        for level in ("68", "95"):
            hits = [x[f"in{level}"] for x in mine if x[f"in{level}"] is not None]
            share = float(np.mean(hits)) if hits else None
            n_eff = len(hits) / deff if hits else 0.0
            entry[f"coverage{level}"] = share
            entry[f"coverage{level}_ci95"] = wilson_interval(share * n_eff, n_eff) if hits else None
            entry[f"coverage{level}_ci95_if_independent"] = (wilson_interval(int(np.sum(hits)), len(hits))
                                                            if hits else None)
            if level == "95":
                entry["intervals"], entry["intervals_effective"] = len(hits), n_eff
        entry.update(interval_honesty(mine))
        by_effects = {}
        for fx in sorted({x.get("effects", "scene") for x in mine}):
            part = interval_honesty([x for x in mine if x.get("effects", "scene") == fx])
            hits = [x["in95"] for x in mine if x.get("effects", "scene") == fx and x["in95"] is not None]
            by_effects[fx] = {"coverage95": float(np.mean(hits)) if hits else None, **{
                k: part[k] for k in ("errors", "rms_error_over_sigma", "half_width95_over_mean_error",
                                     "coverage95_at_matched_68")}}
        entry["by_effects"] = by_effects
        coverage[q] = entry
    return coverage


#: Nominal levels of the intervals' reliability curve (``interval_honesty``).
RELIABILITY_LEVELS = (0.5, 0.6827, 0.8, 0.9, 0.95, 0.99)
#: A Gaussian error with the stated sigma: mean 95 % half-width over mean |error|, 1.96 / sqrt(2 / pi).
GAUSSIAN_HALF_WIDTH_RATIO = 1.959963984540054 / math.sqrt(2.0 / math.pi)


def interval_honesty(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """How honest a set of intervals is, beyond its coverage (rows of one quantity, each with
    ``value``, ``truth``, ``sigma`` and, where known, ``half95``, its 95 % interval's half-width):

    - ``rms_error_over_sigma``: the RMS of ``z = (value - truth) / sigma``, 1 where the sigmas
      are right (below 1: wide, above: short);
    - ``half_width95_over_mean_error``: the mean 95 % half-width over the mean |error|, the
      issue's "within 3x the actual error on average"; a Gaussian error with the stated sigma
      gives ``GAUSSIAN_HALF_WIDTH_RATIO`` (2.46);
    - ``reliability``: per nominal level p of ``RELIABILITY_LEVELS``, the share of |z| within
      the Gaussian's two-sided p quantile (p where the errors are Gaussian with those sigmas);
    - ``z68``: the 68.27 % quantile of |z| (1 where the sigmas are right; a sigma would have to
      be this many times its size for its 68 % interval to cover as nominal), and
      ``coverage95_at_matched_68``: the share of |z| within 1.96 ``z68``, the 95 % coverage the
      intervals would have once rescaled to cover 68 % exactly. 95 % for Gaussian errors of any
      scale; above it the errors have lighter tails than a Gaussian (bounded: a shared bias,
      say), so that no rescaling brings both levels to nominal, and a 95 % coverage above 95 %
      says the tails, not the width, where the 68 % coverage is right.
    """
    from statistics import NormalDist

    ok = [x for x in rows if x.get("value") is not None and x.get("truth") is not None and x.get("sigma")]
    out: dict[str, Any] = {"errors": len(ok), "rms_error_over_sigma": None, "half_width95_over_mean_error": None,
                           "reliability": None, "z68": None, "coverage95_at_matched_68": None}
    if not ok:
        return out
    err = np.array([x["value"] - x["truth"] for x in ok], float)
    z = np.abs(err / np.array([x["sigma"] for x in ok], float))
    out["rms_error_over_sigma"] = float(np.sqrt(np.mean(z**2)))
    with_half = [(h, abs(e)) for x, e in zip(ok, err) if (h := x.get("half95")) is not None]
    if with_half and sum(e for _, e in with_half) > 0:
        out["half_width95_over_mean_error"] = float(np.mean([h for h, _ in with_half])
                                                    / np.mean([e for _, e in with_half]))
    gauss = NormalDist()
    out["reliability"] = [{"nominal": p, "observed": float(np.mean(z <= gauss.inv_cdf(0.5 + p / 2)))}
                          for p in RELIABILITY_LEVELS]
    z68 = float(np.quantile(z, 0.6827))
    out["z68"] = z68
    out["coverage95_at_matched_68"] = float(np.mean(z <= 1.959963984540054 * z68)) if z68 > 0 else None
    return out
