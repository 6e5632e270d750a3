"""Benchmark report: results.json, report.md and a self-contained report.html (plots inline).

Contents: estimated vs true per case with relative errors and pass/fail against the suite's
tolerances; error distributions and estimated-vs-true scatter; the price of accuracy (error
against render time and against measure + fit time, Pareto front marked); calibration of the
uncertainty (coverage of the 68 % and 95 % intervals, and how honest they are: error over sigma,
half-width over error, the reliability curve and the tails: ``lensfit.bench.coverage``);
efficiency (observed scatter over seeds against the Cramer-Rao lower bound of the same capture);
provenance.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.bench.coverage import (GAUSSIAN_HALF_WIDTH_RATIO, RELIABILITY_LEVELS, coverage_summary,  # noqa: F401
                                    design_effect, interval_honesty, wilson_interval)
from lensfit.bench.suites import QUANTITIES, Suite
from lensfit.outputs.writers import write_text

CONFIG_KEYS = ("scene", "render", "effects", "noise", "estimator", "solver")


def report_rows(records: list[dict[str, Any]], tolerances: dict[str, float]) -> list[dict[str, Any]]:
    """One row per case x setting x quantity."""
    rows = []
    for r in records:
        for label, qs in (r.get("settings") or {}).items():
            for q in QUANTITIES:
                e = qs.get(q)
                if e is None:
                    continue
                err = e["relative_error"]
                inside = {}
                for level in ("ci68", "ci95"):
                    ci, t = e.get(level), e["truth"]
                    if ci is None or t is None:
                        inside[level] = None
                    else:
                        inside[level] = (ci[0] is None or ci[0] <= t) and (ci[1] is None or t <= ci[1])
                ci95 = e.get("ci95")
                half95 = (0.5 * (ci95[1] - ci95[0]) if ci95 is not None and None not in ci95 else None)
                rows.append({**{k: r[k] for k in CONFIG_KEYS}, "seed": r["seed"], "setting": label, "quantity": q,
                             "truth": e["truth"], "value": e["value"], "sigma": e["sigma"], "crlb": e.get("crlb"),
                             "half95": half95,
                             "relative_error": err, "in68": inside["ci68"], "in95": inside["ci95"],
                             "passed": None if err is None else abs(err) <= tolerances[q],
                             "refused": e["value"] is None and not e.get("infinite", False)})
    return rows


#: Seeds a configuration needs before its scatter is estimated (two draws give a standard
#: deviation with 100 % relative uncertainty; three, about 50 %).
MIN_SEEDS_FOR_SCATTER = 3


def summarise(records: list[dict[str, Any]], suite: Suite) -> dict[str, Any]:
    """Per-configuration figures (over seeds and settings) and the Pareto fronts."""
    for r in records:
        r.setdefault("effects", "scene")  # case files from before the effects axis
    rows = report_rows(records, suite.tolerances)
    configs: dict[tuple, dict[str, Any]] = {}
    for r in records:
        key = tuple(r[k] for k in CONFIG_KEYS)
        c = configs.setdefault(key, {**dict(zip(CONFIG_KEYS, key)), "cases": 0, "render_s": [], "fit_s": []})
        c["cases"] += 1
        c["render_s"].append(r["seconds_render"])
        if r.get("seconds_fit") is not None:
            c["fit_s"].append(r["seconds_measure"] + r["seconds_fit"])
    out = []
    for key, c in configs.items():
        mine = [x for x in rows if tuple(x[k] for k in CONFIG_KEYS) == key]
        errs = np.array([x["relative_error"] for x in mine if x["relative_error"] is not None])
        entry = {k: c[k] for k in CONFIG_KEYS}
        entry.update({"cases": c["cases"], "seconds_render": float(np.median(c["render_s"])),
                      "seconds_measure_fit": float(np.median(c["fit_s"])) if c["fit_s"] else None,
                      "rms_relative_error": float(np.sqrt(np.mean(errs**2))) if errs.size else None,
                      "refused": sum(x["refused"] for x in mine), "quantities": {}})
        for q in QUANTITIES:
            sel = [x for x in mine if x["quantity"] == q]
            vals = [x for x in sel if x["value"] is not None and x["truth"]]
            e = np.array([x["relative_error"] for x in vals])
            # Scatter over seeds, per setting, relative to the truth; then averaged over settings.
            scat, crlb, stated = [], [], []
            for label in {x["setting"] for x in vals}:
                v = [x for x in vals if x["setting"] == label]
                if len(v) >= MIN_SEEDS_FOR_SCATTER:
                    scat.append(float(np.std([x["value"] for x in v], ddof=1)) / v[0]["truth"])
                crlb += [x["crlb"] / x["truth"] for x in v if x["crlb"] is not None]
                stated += [x["sigma"] / x["truth"] for x in v if x["sigma"] is not None]
            n68 = [x["in68"] for x in sel if x["in68"] is not None]
            n95 = [x["in95"] for x in sel if x["in95"] is not None]
            entry["quantities"][q] = {
                "rms_relative_error": float(np.sqrt(np.mean(e**2))) if e.size else None,
                "bias": float(np.mean(e)) if e.size else None,
                "passed": int(sum(bool(x["passed"]) for x in sel)), "total": len(sel),
                "observed_scatter": float(np.mean(scat)) if scat else None,
                "stated_sigma": float(np.median(stated)) if stated else None,
                "crlb": float(np.median(crlb)) if crlb else None,
                "coverage68": float(np.mean(n68)) if n68 else None, "coverage95": float(np.mean(n95)) if n95 else None,
            }
            qd = entry["quantities"][q]
            qd["efficiency"] = (qd["crlb"] / qd["observed_scatter"]) if qd["crlb"] and qd["observed_scatter"] else None
        out.append(entry)
    for axis in ("seconds_render", "seconds_measure_fit"):
        for scene in {c["scene"] for c in out}:  # times of different scenes do not compare
            mine = [c for c in out if c["scene"] == scene]
            for c, on in zip(mine, pareto([(c[axis], c["rms_relative_error"]) for c in mine])):
                c[f"pareto_{axis}"] = on
    return {"rows": rows, "configurations": out, "coverage": coverage_summary(rows)}


def pareto(points: list[tuple[float | None, float | None]]) -> list[bool]:
    """Whether each (time, error) point is on the Pareto front (no other point is at least as
    good in both and better in one). Points with a missing coordinate are not."""
    out = []
    for i, (t, e) in enumerate(points):
        if t is None or e is None:
            out.append(False)
            continue
        dominated = any(t2 is not None and e2 is not None and t2 <= t and e2 <= e and (t2 < t or e2 < e)
                        for j, (t2, e2) in enumerate(points) if j != i)
        out.append(not dominated)
    return out


# --------------------------------------------------------------------------- plots


def _readable_log_ticks(ax) -> None:
    """Plain numbers at 1-2-5 steps on log axes, no labels on the minor ticks (they overlapped)."""
    from matplotlib.ticker import LogLocator, NullFormatter, StrMethodFormatter

    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0), numticks=8))
        axis.set_major_formatter(StrMethodFormatter("{x:.3g}"))
        axis.set_minor_formatter(NullFormatter())


def _plots(summary: dict[str, Any]) -> dict[str, bytes]:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    rows, configs = summary["rows"], summary["configurations"]
    figs: dict[str, Any] = {}
    names = {"focal_length_mm": "focal length", "f_number": "f-number", "focus_distance_mm": "focus distance"}

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8), layout="constrained")
    estimators = sorted({r["estimator"] for r in rows}) or ["-"]
    rng = np.random.default_rng(0)
    for ax, q in zip(axes, QUANTITIES):
        for i, est in enumerate(estimators):
            e = [100 * r["relative_error"] for r in rows if r["quantity"] == q and r["estimator"] == est
                 and r["relative_error"] is not None]
            ax.plot(i + rng.uniform(-0.15, 0.15, len(e)), e, "o", ms=4, alpha=0.6)
            if e:
                ax.hlines(np.median(e), i - 0.3, i + 0.3, color="k")
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xticks(range(len(estimators)), estimators)
        ax.set_title(f"{names[q]}: relative error (%)")
        ax.grid(alpha=0.3)
    figs["errors"] = fig

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8), layout="constrained")
    for ax, q in zip(axes, QUANTITIES):
        pts = [(r["truth"], r["value"]) for r in rows if r["quantity"] == q and r["value"] is not None and r["truth"]]
        if pts:
            t, v = np.array(pts).T
            ax.plot(t, v, "o", ms=4, alpha=0.6)
            lo, hi = min(t.min(), v.min()), max(t.max(), v.max())
            ax.plot([lo, hi], [lo, hi], "k-", lw=0.8)
        ax.set_xlabel("true")
        ax.set_ylabel("estimated")
        ax.set_title(names[q])
        ax.grid(alpha=0.3)
    figs["estimated_vs_true"] = fig

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
    for ax, axis, label in ((axes[0], "seconds_render", "render time per stack (s)"),
                            (axes[1], "seconds_measure_fit", "measure + fit time per stack (s)")):
        pts = [(c[axis], 100 * c["rms_relative_error"], c) for c in configs
               if c[axis] is not None and c["rms_relative_error"] is not None]
        # Only the Pareto-optimal configurations are named (the others would overlap); labels
        # alternate above and below their point, and name what differs between them.
        front_pts = sorted(((t, e, c) for t, e, c in pts if c[f"pareto_{axis}"]), key=lambda p: p[0])
        varying = [k for k in ("render", "effects", "noise", "estimator", "solver")
                   if len({c[k] for _, _, c in pts}) > 1] or ["render"]
        for t, e, c in pts:
            on = c[f"pareto_{axis}"]
            ax.plot(t, e, "o", ms=7 if on else 5, color="C3" if on else "0.6", alpha=0.9 if on else 0.6,
                    zorder=3 if on else 2)
        for j, (t, e, c) in enumerate(front_pts):
            ax.annotate(", ".join(str(c[k]) for k in varying), (t, e), fontsize=7,
                        xytext=(4, 8 if j % 2 == 0 else -12), textcoords="offset points",
                        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})
        for i, scene in enumerate(sorted({c["scene"] for _, _, c in pts})):
            front = sorted((t, e) for t, e, c in pts if c[f"pareto_{axis}"] and c["scene"] == scene)
            if front:
                ax.step(*zip(*front), where="post", color="C3", lw=1.2, ls=("-", "--", ":", "-.")[i % 4],
                        label=f"Pareto front: {scene}")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
        ax.set_xlabel(label)
        ax.set_ylabel("RMS relative error of f, N, focus (%)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        _readable_log_ticks(ax)
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("The price of accuracy (red: Pareto-optimal, named; grey: dominated)")
    figs["price_of_accuracy"] = fig

    fig, (ax, rel) = plt.subplots(1, 2, figsize=(11, 3.8), layout="constrained", width_ratios=(1.4, 1))
    cov = summary["coverage"]
    x = np.arange(len(QUANTITIES))
    for shift, level, colour in ((-0.2, "68", "C0"), (0.2, "95", "C1")):
        values = [100 * (cov[q][f"coverage{level}"] or 0) for q in QUANTITIES]
        ci = [cov[q][f"coverage{level}_ci95"] or [0.0, 0.0] for q in QUANTITIES]
        err = np.array([[v - 100 * c[0] for v, c in zip(values, ci)], [100 * c[1] - v for v, c in zip(values, ci)]])
        ax.bar(x + shift, values, 0.4, color=colour, label=f"{level} % interval",
               yerr=np.maximum(err, 0.0), capsize=3, error_kw={"lw": 0.8})
    ax.axhline(68.27, color="C0", ls="--", lw=1)
    ax.axhline(95.45, color="C1", ls="--", lw=1)
    ax.set_xticks(x, [names[q] for q in QUANTITIES])
    ax.set_ylabel("intervals holding the truth (%)\n(bars: binomial 95 % interval,\neffective count)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title("Calibration of the uncertainty")
    rel.plot([0, 100], [0, 100], color="0.6", lw=1, ls="--", label="Gaussian errors, right sigmas")
    for q, marker in zip(QUANTITIES, "osd^v"):
        curve = cov[q].get("reliability")
        if curve:
            rel.plot([100 * c["nominal"] for c in curve], [100 * c["observed"] for c in curve], marker=marker,
                     ms=4, lw=1, label=names[q])
    rel.set_xlabel("nominal level (%)")
    rel.set_ylabel("errors within that many sigmas (%)")
    rel.set_xlim(45, 100)
    rel.set_ylim(45, 101)
    rel.grid(alpha=0.3)
    rel.legend(fontsize=7, loc="lower right")
    rel.set_title("Reliability: above the line, sigmas wide")
    figs["coverage"] = fig

    fig, ax = plt.subplots(figsize=(6, 5), layout="constrained")
    for i, q in enumerate(QUANTITIES):
        pts = [(c["quantities"][q]["crlb"], c["quantities"][q]["observed_scatter"]) for c in configs
               if c["quantities"][q]["crlb"] and c["quantities"][q]["observed_scatter"]]
        if pts:
            b, s = np.array(pts).T * 100
            ax.plot(b, s, "o", color=f"C{i}", label=names[q])
    lims = ax.get_xlim() + ax.get_ylim()
    if all(np.isfinite(lims)) and min(lims) > 0:
        lo, hi = min(lims), max(lims)
    else:
        lo, hi = 0.01, 10.0
    ax.plot([lo, hi], [lo, hi], "k-", lw=0.8, label="scatter = bound (efficient)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    _readable_log_ticks(ax)
    ax.set_xlabel("Cramer-Rao lower bound (relative %, 1 sigma)")
    ax.set_ylabel("observed scatter over seeds (relative %)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, f"needs {MIN_SEEDS_FOR_SCATTER}+ seeds per configuration", ha="center",
                transform=ax.transAxes)
    ax.grid(alpha=0.3, which="both")
    ax.set_title("Efficiency")
    figs["efficiency"] = fig

    out = {}
    for name, fig in figs.items():
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=100)
        plt.close(fig)
        out[name] = buf.getvalue()
    return out


# --------------------------------------------------------------------------- documents


def _pct(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{100 * x:+.{digits}f}%"


def _num(x: float | None, spec: str = ".3g") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _tables(summary: dict[str, Any], suite: Suite) -> list[tuple[str, list[str], list[list[str]]]]:
    cases = [[r["scene"], r["render"], r["effects"], r["noise"], r["estimator"], r["solver"], str(r["seed"]), r["setting"],
              r["quantity"], _num(r["truth"], ".6g"), "refused" if r["refused"] else _num(r["value"], ".6g"),
              _num(r["sigma"]), _pct(r["relative_error"]),
              "-" if r["passed"] is None else ("pass" if r["passed"] else "FAIL")] for r in summary["rows"]]
    configs = []
    for c in summary["configurations"]:
        for q in QUANTITIES:
            d = c["quantities"][q]
            configs.append([c["scene"], c["render"], c["effects"], c["noise"], c["estimator"], c["solver"], q,
                            _pct(d["rms_relative_error"]).lstrip("+"), _pct(d["bias"]), f"{d['passed']}/{d['total']}",
                            _pct(d["observed_scatter"], 4).lstrip("+"), _pct(d["stated_sigma"], 4).lstrip("+"),
                            _pct(d["crlb"], 4).lstrip("+"), _num(d["efficiency"], ".2f"),
                            _pct(d["coverage68"], 0).lstrip("+"), _pct(d["coverage95"], 0).lstrip("+")])
    price = [[c["scene"], c["render"], c["effects"], c["noise"], c["estimator"], c["solver"], _num(c["seconds_render"]),
              _num(c["seconds_measure_fit"]), _pct(c["rms_relative_error"]).lstrip("+"),
              ("render " if c["pareto_seconds_render"] else "") + ("fit" if c["pareto_seconds_measure_fit"] else "")]
             for c in summary["configurations"]]
    def with_ci(v, level):
        ci = v.get(f"coverage{level}_ci95")
        text = _pct(v[f"coverage{level}"], 0).lstrip("+")
        return text + (f" ({100 * ci[0]:.0f}-{100 * ci[1]:.0f})" if ci else "")

    cov = [[q, with_ci(v, "68"), with_ci(v, "95"), str(v["intervals"]),
            f"{v.get('intervals_effective', v['intervals']):.0f} ({v.get('clusters', '-')} renders)",
            _num(v.get("rms_error_over_sigma"), ".2f"), _num(v.get("half_width95_over_mean_error"), ".2f"),
            _pct(v.get("coverage95_at_matched_68"), 0).lstrip("+")]
           for q, v in summary["coverage"].items()]
    honesty = [[q, fx, str(d["errors"]), _pct(d["coverage95"], 0).lstrip("+"), _num(d["rms_error_over_sigma"], ".2f"),
                _num(d["half_width95_over_mean_error"], ".2f"), _pct(d["coverage95_at_matched_68"], 0).lstrip("+")]
               for q, v in summary["coverage"].items() for fx, d in v.get("by_effects", {}).items()]
    tol = ", ".join(f"{q} {100 * v:g}%" for q, v in suite.tolerances.items())
    return [
        ("Estimated versus true, per case", ["scene", "render", "effects", "noise", "estimator", "solver", "seed", "setting",
                                              "quantity", "truth", "estimate", "sigma", "error", f"within ({tol})"],
         cases),
        ("Per configuration (over seeds and settings)", ["scene", "render", "effects", "noise", "estimator", "solver", "quantity",
                                                          "RMS error", "bias", "passed", "observed scatter",
                                                          "stated sigma", "CRLB", "CRLB/scatter", "in 68%",
                                                          "in 95%"], configs),
        ("The price of accuracy (median seconds per stack; Pareto front per scene marked)",
         ["scene", "render", "effects", "noise", "estimator", "solver", "render s", "measure+fit s", "RMS error",
          "Pareto"], price),
        ("Calibration of the uncertainty (all cases; in brackets the binomial 95 % interval of the coverage, "
         "over the effective number of intervals: those of one render share its errors)",
         ["quantity", "in 68% interval", "in 95% interval", "intervals", "effectively independent",
          "RMS error / sigma (1 if right)", f"95% half-width / mean error ({GAUSSIAN_HALF_WIDTH_RATIO:.2f} if right)",
          "95% coverage, intervals rescaled to 68% nominal (95% for Gaussian errors)"], cov),
        ("Honesty of the intervals per effects set", ["quantity", "effects", "errors", "in 95% interval",
                                                       "RMS error / sigma", "95% half-width / mean error",
                                                       "95% at matched 68%"], honesty),
    ]


def write_report(records: list[dict[str, Any]], suite: Suite, prov: dict[str, Any], out: str | Path) -> dict[str, Path]:
    """Write results.json, report.md (+ plots/*.png) and report.html into ``out``."""
    out = Path(out)
    summary = summarise(records, suite)
    plots = _plots(summary)
    (out / "plots").mkdir(parents=True, exist_ok=True)
    for name, png in plots.items():
        (out / "plots" / f"{name}.png").write_bytes(png)
    doc = {"provenance": prov, "suite": {"name": suite.name, "description": suite.description,
                                         "tolerances": suite.tolerances},
           "cases": records, "configurations": summary["configurations"], "coverage": summary["coverage"]}
    files = {"json": out / "results.json", "md": out / "report.md", "html": out / "report.html"}
    write_text(files["json"], json.dumps(doc, indent=1, allow_nan=False))
    tables = _tables(summary, suite)
    refused = [r for r in records if r.get("error") or r.get("reasons")]
    title = f"lensfit benchmark: suite {suite.name}"
    prov_lines = [f"{k}: {v}" for k, v in prov.items()]

    md = [f"# {title}", "", suite.description, "", f"{len(records)} cases. Tolerances: "
          + ", ".join(f"{q} {100 * v:g}%" for q, v in suite.tolerances.items()), ""]
    for name, caption in (("price_of_accuracy", "Error against time, Pareto front in red"),
                          ("errors", "Error distributions"), ("estimated_vs_true", "Estimated versus true"),
                          ("coverage", "Coverage of the intervals"), ("efficiency", "Scatter against the bound")):
        md += [f"![{caption}](plots/{name}.png)", ""]
    for heading, header, body in tables:
        md += [f"## {heading}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        md += ["| " + " | ".join(row) + " |" for row in body]
        md.append("")
    if refused:
        md += ["## Refusals and errors", ""] + [f"- {r['id']} ({r['scene']}, {r['render']}, {r['effects']}, {r['noise']}, seed "
                                               f"{r['seed']}): {r.get('error') or '; '.join(r['reasons'])}"
                                               for r in refused] + [""]
    md += ["## Provenance", ""] + [f"- {line}" for line in prov_lines] + [""]
    write_text(files["md"], "\n".join(md))

    e = html.escape
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{e(title)}</title>",
             "<style>body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;"
             "font-size:12px}.scroll{overflow-x:auto;max-width:100%;margin-bottom:2em}"
             "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
             "th{background:#eee}td:first-child,th:first-child{text-align:left}.FAIL{color:#b00;font-weight:bold}"
             "img{max-width:100%}</style></head><body>", f"<h1>{e(title)}</h1>", f"<p>{e(suite.description)}</p>",
             f"<p>{len(records)} cases.</p>"]
    for name, caption in (("price_of_accuracy", "The price of accuracy: error against time, Pareto front in red"),
                          ("errors", "Error distributions per parameter and estimator"),
                          ("estimated_vs_true", "Estimated versus true"),
                          ("coverage", "Calibration of the uncertainty"),
                          ("efficiency", "Efficiency: observed scatter against the Cramer-Rao lower bound")):
        data = base64.b64encode(plots[name]).decode()
        parts.append(f"<h2>{e(caption)}</h2><img alt='{e(caption)}' src='data:image/png;base64,{data}'>")
    for heading, header, body in tables:
        parts.append(f"<h2>{e(heading)}</h2><div class='scroll'><table><tr>"
                     + "".join(f"<th>{e(h)}</th>" for h in header) + "</tr>")
        for row in body:
            parts.append("<tr>" + "".join(f"<td class='{e(c)}'>{e(c)}</td>" if c == "FAIL" else f"<td>{e(c)}</td>"
                                          for c in row) + "</tr>")
        parts.append("</table></div>")
    if refused:
        parts.append("<h2>Refusals and errors</h2><ul>" + "".join(
            f"<li>{e(r['id'])}: {e(r.get('error') or '; '.join(r['reasons']))}</li>" for r in refused) + "</ul>")
    parts.append("<h2>Provenance</h2><ul>" + "".join(f"<li>{e(line)}</li>" for line in prov_lines) + "</ul>")
    parts.append("</body></html>")
    write_text(files["html"], "\n".join(parts))
    return files

