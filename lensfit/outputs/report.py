"""One HTML page per fit (``lensfit fit --report report.html``): what was found and what it was
found from.

Self-contained (pictures inline as PNG data), readable offline and mailable:

1. the estimates per setting with 1-sigma and 95 % intervals (and the truth where the stack
   has a truth.json), the fit's statistics, warnings and the reasons for any refusal;
2. the fit plot (blur versus inverse distance with the fitted V, residuals);
3. one overlay per image (a stack fit, where the images are at hand): left, the image with
   the detected corners (crosses) and every measured edge drawn where it was measured,
   coloured by its blur diameter (px); right, the same edges coloured by residual / sigma
   (measured minus model, in units of the edge's stated sigma; blue below the model, red
   above, dashed where the robust loss down-weighted the edge, dotted magenta where nothing was
   measured). A per-image table gives the corners found and how far they reproject from the
   calibration, edges read and why the others were not, distances and the RMS residual: a bad
   image (a moved target, a wrong setting label, motion blur) stands out there;
4. where the boards were: each board's outline seen from above (camera at the origin, looking
   up the page) and from the side, coloured by setting, with each setting's fitted focus
   distance.

Matplotlib (Agg) draws; nothing is shown on screen.
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.fitting import FitResult
from lensfit.outputs.plots import DOWN_WEIGHTED
from lensfit.io.samples import SampleTable


def budget_text(quantities: dict[str, Any]) -> str:
    """"variance from: ...": per headline quantity of a setting, the sources carrying at least a
    tenth of its variance, largest first ("" where none is known)."""
    parts = []
    for qn in ("focal_length_mm", "f_number", "focus_distance_mm"):
        est = quantities.get(qn)
        shares = est.shares if est is not None and est.value is not None else None
        big = sorted(((v, k) for k, v in (shares or {}).items() if v >= 0.1), reverse=True)
        if big:
            parts.append(f"{qn} " + ", ".join(f"{k.replace('_', ' ')} {100 * v:.0f}%" for v, k in big))
    return "variance from: " + "; ".join(parts) if parts else ""


def calibration_text(cal: dict[str, Any] | None) -> str:
    """"calibration: focal length ... px (how its sigma was found, views, reprojection RMS)" for a
    setting's entry of the results' ``calibration`` ("" where it was not calibrated)."""
    if not cal or cal.get("source") != "calibrated":
        return ""
    how = cal.get("focal_length_sigma_method") or "sigma"
    views = f"{cal['views']} views"
    if cal.get("informative_views"):  # a jackknife, pooled with the corners' model
        how += " with the corners' model"
        views = f"{cal['informative_views']:.1f} informative of {views}"
    text = (f"calibration: focal length {cal['focal_length_px']:.1f} ± {cal['focal_length_sigma_px']:.2g} px "
            f"({how}, {views}, reprojection RMS {cal['rms_px']:.3g} px)")
    fov = cal.get("field_of_view_deg")
    if fov:
        h, v, d = fov["horizontal"], fov["vertical"], fov["diagonal"]
        text += (f"; angle of view {h['value']:.2f} x {v['value']:.2f} deg, diagonal {d['value']:.2f} deg "
                 f"[{d['ci95'][0]:.2f}, {d['ci95'][1]:.2f}]")
    return text

def assumptions_text(table: SampleTable, document: dict[str, Any]) -> str:
    """"assumptions: ...": what the fit took as given rather than measured: how the lens focuses,
    where its pupil magnification came from, which f-number is reported, how the images were
    encoded."""
    lens = table.lens or {}
    p = document.get("pupil_magnification") or {}
    parts = [f"focusing {lens.get('focusing', 'unknown')}"
             + ("" if "focusing" in lens else " (not declared: each setting fitted by itself)"),
             f"pupil magnification {p.get('reason') or p.get('source') or 'unknown'}"]
    definition = document.get("f_number_definition") or {}
    if definition.get("note"):
        parts.append(f"f-number {definition.get('reported')}: {definition['note']}")
    proc = document.get("processing") or {}
    if proc.get("f_number_modelled"):
        model = proc.get("model") or {}
        share = 100 * math.hypot(model.get("f_number_spread", 0.0), model.get("f_number_model_sigma", 0.0))
        parts.append(f"developed images read through a tone curve and an unsharp mask fitted to the edges (amount "
                     f"{model.get('sharpening_amount', 0.0):.2f} at {model.get('sharpening_sigma_px', 0.0):.2f} px; "
                     f"N's interval carries {share:.1f} % for the model)")
    elif proc.get("developer") or proc.get("halos"):
        parts.append(f"developed images ({proc.get('developer') or 'sharpening halos'})")
    elif proc.get("tone_mismatch"):
        parts.append("a tone curve the declared encoding does not undo (edges "
                     f"{proc.get('tone_offset'):+.3f} of a blur radius off the corners' lines)")
    elif proc:
        parts.append("images read as " + ("sRGB-encoded" if proc.get("encoded") else "linear"))
    return "assumptions: " + "; ".join(parts)


#: Overlays wider than this (px) are drawn downscaled (the picture, not the measurement).
OVERLAY_WIDTH_PX = 1400
#: |residual| / sigma above which an edge is listed as suspicious.
SUSPICIOUS_SIGMAS = 3.0


def tone_figure(model: dict[str, Any]):
    """The tone curve fitted to a developed stack's edges against the encoding its files declare,
    and the unsharp mask's profile across an edge (``processing.model`` of the results)."""
    import matplotlib.pyplot as plt

    curve = np.asarray(model["tone_curve"], np.float64)
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.4))
    left.plot(curve[:, 0], curve[:, 2], "--", color="grey", label=f"declared ({model.get('encoding', '')})")
    left.plot(curve[:, 0], curve[:, 1], color="C0", label="fitted to the edges")
    left.set(xlabel="linear light", ylabel="file value", title="tone curve")
    left.legend(loc="lower right")
    x = np.linspace(-5.0, 5.0, 401)
    sigma, amount = max(model["sharpening_sigma_px"], 1e-3), model["sharpening_amount"]
    step = (x > 0).astype(float)
    from scipy.special import erf

    blurred = 0.5 * (1.0 + erf(x / (sigma * math.sqrt(2.0))))
    right.plot(x, step + amount * (step - blurred), color="C1")
    right.set(xlabel="px across an edge", ylabel="file value", title=f"unsharp mask: {amount:.2f} at {sigma:.2f} px")
    fig.tight_layout()
    return fig


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def edge_values(table: SampleTable, result: FitResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample of ``table``: blur (NaN where unmeasured), residual / sigma and robust weight
    (NaN where the fit did not use it)."""
    n = len(table.samples)
    blur = np.array([np.nan if s.coc_diameter_px is None else s.coc_diameter_px for s in table.samples], float)
    z = np.full(n, np.nan)
    w = np.full(n, np.nan)
    data = result.samples
    if data is not None and len(getattr(data, "row", ())) == len(result.residuals_px):
        z[data.row] = result.residuals_px / data.sigma_px
        w[data.row] = result.weights
    return blur, z, w


def overlay_figure(image: np.ndarray, name: str, samples: list, blur: np.ndarray, z: np.ndarray, w: np.ndarray,
                   corners: list[tuple[str, np.ndarray]], blur_range: tuple[float, float]):
    """The two-panel overlay of one image (see the module notes); a matplotlib Figure."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib import patheffects
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    from lensfit.calibration.targets import display_8bit

    grey = image if image.ndim == 2 else image.mean(axis=-1)
    shown = display_8bit(grey, gamma=2.2)
    h, w_px = shown.shape
    aspect = h / w_px
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.4 * aspect + 0.9), layout="constrained")
    segments = np.array([[s.start_px, s.end_px] for s in samples], float).reshape(-1, 2, 2)
    norm_blur = Normalize(*blur_range)
    norm_z = Normalize(-4.0, 4.0)
    for ax, values, norm, cmap, label in ((axes[0], blur, norm_blur, "viridis", "blur-disk diameter (px)"),
                                          (axes[1], z, norm_z, "coolwarm", "residual / sigma")):
        ax.imshow(shown, cmap="gray", vmin=0, vmax=255, interpolation="antialiased")
        ok = np.isfinite(values)
        if (~ok).any():
            ax.add_collection(LineCollection(segments[~ok], colors="magenta", linewidths=1.6, linestyles=":"))
        if ok.any():
            styles = ["--" if (np.isfinite(wt) and wt < DOWN_WEIGHTED) else "-" for wt in w[ok]]
            lc = LineCollection(segments[ok], cmap=cmap, norm=norm, linewidths=2.6, linestyles=styles)
            lc.set_array(np.clip(values[ok], norm.vmin, norm.vmax))
            # a dark casing keeps the pale middle of the colour scale legible on the white board
            lc.set_path_effects([patheffects.Stroke(linewidth=4.2, foreground="black"), patheffects.Normal()])
            ax.add_collection(lc)
            fig.colorbar(lc, ax=ax, shrink=0.8, label=label)
        for _, pts in corners:
            if len(pts):
                ax.plot(pts[:, 0], pts[:, 1], "+", color="orange", ms=5, mew=0.8)
        ax.set_xlim(0, w_px)
        ax.set_ylim(h, 0)
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0].set_title(f"{name}: detected corners (+) and measured edges", fontsize=10)
    axes[1].set_title("residual of each edge (dashed: down-weighted; dotted magenta: not measured)", fontsize=10)
    return fig


def samples_by_image(table: SampleTable) -> dict[str, np.ndarray]:
    """Image name -> indices of its samples in ``table`` (images in order of first sample)."""
    groups: dict[str, list[int]] = {}
    for i, s in enumerate(table.samples):
        groups.setdefault(s.image, []).append(i)
    return {name: np.array(idx) for name, idx in groups.items()}


def _flag_counts(flags: list[tuple[str, ...]]) -> str:
    """"radial_profile 3, short_edge 1": the flags of some edges, most frequent first."""
    counts: dict[str, int] = {}
    for some in flags:
        for flag in some:
            counts[flag] = counts.get(flag, 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def image_rows(table: SampleTable, blur: np.ndarray, z: np.ndarray, w: np.ndarray,
               images: list[tuple[str, str]] = ()) -> list[dict[str, Any]]:
    """Per image: setting, corners found and their reprojection RMS from the calibration, edges
    found / measured / used, why edges were not measured (their flags) and the measured edges'
    flags, distance range, RMS residual / sigma and the number of suspicious and down-weighted
    edges. ``images``: (name, setting) of every image of the stack, so that those that gave no
    edges get a row saying why."""
    rows = []
    groups = samples_by_image(table)
    for name, setting in images:
        if name not in groups:
            found = sum(len(pts) for _, pts in table.corners_px.get(name, []))
            why = ("its setting left out (see the warnings)" if setting in table.left_out_settings
                   else "no target found" if not found else "target left out (see the warnings)")
            rows.append({"image": name, "setting": setting, "corners": found, "reprojection_rms_px": math.nan,
                         "edges": 0, "measured": 0, "used": 0, "distance_mm": None, "rms_residual_sigma": math.nan,
                         "suspicious": 0, "down_weighted": 0, "flags": "", "not_measured": "",
                         "why_none": why})
    for name, idx in groups.items():
        d = np.array([table.samples[i].distance_mm for i in idx])
        zi = z[idx][np.isfinite(z[idx])]
        poses = [pose for (image, _), pose in table.poses.items() if image == name]
        measured = np.isfinite(blur[idx])
        rows.append({"image": name, "setting": table.samples[idx[0]].setting,
                     "corners": sum(len(pts) for _, pts in table.corners_px.get(name, [])),
                     "reprojection_rms_px": max((p.rms_px for p in poses), default=math.nan),
                     "edges": len(idx), "measured": int(measured.sum()), "used": int(zi.size),
                     "distance_mm": (float(d.min()), float(d.max())),
                     "rms_residual_sigma": float(np.sqrt(np.mean(zi**2))) if zi.size else math.nan,
                     "suspicious": int((np.abs(zi) > SUSPICIOUS_SIGMAS).sum()),
                     "down_weighted": int((w[idx][np.isfinite(w[idx])] < DOWN_WEIGHTED).sum()),
                     "flags": _flag_counts([table.samples[i].flags for i, m in zip(idx, measured) if m]),
                     "not_measured": _flag_counts([table.samples[i].flags or ("unreadable",)
                                                   for i, m in zip(idx, measured) if not m]),
                     "why_none": ""})
    order = {name: k for k, (name, _) in enumerate(images)}
    return sorted(rows, key=lambda r: order.get(r["image"], len(order)))


def _board_outline_mm(entry: dict[str, Any] | None) -> np.ndarray | None:
    """A target's outline in its own frame (5 x 3, mm, closed), or None where its size is unknown."""
    if not entry:
        return None
    if entry.get("kind") == "charuco" and "squares" in entry and "square_mm" in entry:
        w, h = (n * float(entry["square_mm"]) for n in entry["squares"])
    elif isinstance(entry.get("size_mm"), list) and len(entry["size_mm"]) == 2:
        w, h = (float(v) for v in entry["size_mm"])
    else:
        return None
    return np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0], [0, 0, 0]], float)


def pose_figure(table: SampleTable, result: FitResult, targets: list[dict[str, Any]], setting_of: dict[str, str]):
    """Where the boards were (see the module notes); a matplotlib Figure, or None without poses."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if not table.poses:
        return None
    by_id = {t.get("id"): t for t in targets}
    labels = list(dict.fromkeys(setting_of.values())) or ["?"]
    colours = {label: plt.get_cmap("tab10")(k % 10) for k, label in enumerate(labels)}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained")
    for (image, tid), pose in table.poses.items():
        outline = _board_outline_mm(by_id.get(tid))
        pts = pose.to_camera(outline if outline is not None else np.zeros((1, 3)))
        colour = colours.get(setting_of.get(image, "?"), "k")
        for ax, k in ((axes[0], 0), (axes[1], 1)):
            ax.plot(pts[:, k], pts[:, 2], "-" if len(pts) > 1 else "o", color=colour, lw=1.5)
    for label, quantities in result.settings.items():
        est = quantities.get("focus_distance_mm")
        if est is not None and est.value is not None and math.isfinite(est.value):
            for ax in axes:
                ax.axhline(est.value, color=colours.get(label, "k"), ls="--", lw=1)
    for ax, name in ((axes[0], "x (mm, right)"), (axes[1], "y (mm, down)")):
        ax.plot([0], [0], "k^", ms=9)
        ax.set_xlabel(name)
        ax.set_ylabel("z (mm, from the camera)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0].set_title("boards seen from above (dashed: focus distance)", fontsize=10)
    axes[1].set_title("boards seen from the side", fontsize=10)
    handles = [plt.Line2D([], [], color=c, lw=2) for c in colours.values()]
    axes[1].legend(handles, [f"setting {k}" for k in colours], fontsize=8, loc="best")
    return fig


def to_sigma(value: float | None, sigma: float | None, unbounded: str = "") -> str:
    """``value`` to the decimal of its sigma's second significant digit (6 significant digits
    where the sigma is 0 or unknown); ``unbounded`` for an interval end that is None."""
    if value is None:
        return unbounded
    if not sigma or not math.isfinite(sigma) or sigma <= 0:
        return f"{value:.6g}"
    decimals = max(0, 1 - math.floor(math.log10(sigma)))
    return f"{value:.{decimals}f}"


def _estimates_table(result: FitResult, document: dict[str, Any]) -> str:
    truth = {(r["setting"], r["quantity"]): r for r in document.get("truth_comparison", [])}
    head = "<tr><th>setting</th><th>quantity</th><th>estimate</th><th>1 sigma</th><th>95 % interval</th>"
    head += "<th>truth</th><th>error</th></tr>" if truth else "</tr>"
    out = [head]
    for label, qs in result.settings.items():
        for q in ("focal_length_mm", "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm",
                  "sensor_distance_mm", "aperture_diameter_mm", "blur_floor_px"):
            est = qs.get(q)
            if est is None:
                continue
            if est.value is None:
                why = html.escape(est.reason or "")
                cells = [f"<span title='{why}'>not determined</span>" if why else "not determined", "", ""]
            else:
                lo, hi = est.ci95
                cells = [to_sigma(est.value, est.sigma), f"{est.sigma:.2g}",
                         f"[{to_sigma(lo, est.sigma, '-inf')}, {to_sigma(hi, est.sigma, 'inf')}]"]
            row = f"<tr><td>{html.escape(label)}</td><td>{q}</td>" + "".join(f"<td>{c}</td>" for c in cells)
            if truth:
                t = truth.get((label, q))
                if t and t.get("truth") is not None and t.get("relative_error") is not None:
                    inside = "" if t.get("within_ci95", True) else " class='bad'"
                    row += f"<td>{t['truth']:.6g}</td><td{inside}>{100 * t['relative_error']:+.3f} %</td>"
                else:
                    row += "<td></td><td></td>"
            out.append(row + "</tr>")
    return "<div class='scroll'><table>" + "".join(out) + "</table></div>"


_CSS = """body{font-family:system-ui,sans-serif;max-width:1350px;margin:1em auto;padding:0 1em;color:#222}
.scroll{overflow-x:auto;max-width:100%}code{overflow-wrap:anywhere}p{overflow-wrap:anywhere}
table{border-collapse:collapse;margin:.5em 0;font-size:90%}td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}
td.text{text-align:left}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}.bad{color:#b00;font-weight:bold}
img{max-width:100%}.warn{color:#a60}.note{color:#555;font-size:90%}h2{margin-top:1.5em}"""


def write_fit_report(path: str | Path, result: FitResult, document: dict[str, Any], table: SampleTable,
                     stack=None, *, title: str = "lensfit fit", progress=None) -> None:
    """Write the report (see the module notes). ``stack``: the :class:`lensfit.io.stack.Stack` the
    samples were measured on (None: no overlays, e.g. a refit from a samples file)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from lensfit import __version__
    from lensfit.outputs.writers import software_tag
    from lensfit.outputs.plots import plot_fit

    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'>"
             f"<meta name=\"generator\" content=\"{software_tag('lensfit')}\">"
             f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>",
             f"<p class='note'>lensfit {__version__}; {result.n_samples} edges used, "
             f"{int(np.sum(result.weights < DOWN_WEIGHTED))} down-weighted (robust weight below {DOWN_WEIGHTED:g}), "
             f"{result.n_outliers} beyond 5 robust scales; "
             f"RMS residual {result.rms_residual_px:.3g} px, reduced chi-square {result.chi2_reduced:.3g}, "
             f"loss {result.loss}; pupil magnification "
             + (f"P = {result.pupil_magnification.value:.4g} ({result.pupil_magnification_source})"
                if result.pupil_magnification.value is not None else
                f"P {html.escape(result.pupil_magnification.reason or 'not determined')}")
             + "; distances from the entrance pupil.</p>",
             f"<p class='note'>{html.escape(assumptions_text(table, document))}</p>",
             f"<h2>Estimates: fit {html.escape(result.code)}</h2>", _estimates_table(result, document)]
    for label, quantities in result.settings.items():
        lines = [text for text in (budget_text(quantities),
                                   calibration_text((document.get("calibration") or {}).get(label))) if text]
        if lines:
            parts.append(f"<p class='note'>setting {html.escape(label)}: " + "<br>".join(map(html.escape, lines))
                         + "</p>")
    if "diffraction" in document:
        d = document["diffraction"]
        parts.append(f"<p class='note'>diffraction modelled at {d['wavelength_nm']:g} nm ({d['mode']}; "
                     f"{d['rounds']} round(s) of measuring)</p>")
    prov = document.get("provenance") or {}
    if prov.get("command"):
        parts.append(f"<p class='note'>command: <code>{html.escape(str(prov['command']))}</code>"
                     + (f"; {html.escape(str(prov['date']))}" if prov.get("date") else "") + "</p>")
    for reason in result.reasons:
        parts.append(f"<p class='bad'>{html.escape(reason)}</p>")
    for warning in [*table.warnings, *result.warnings]:
        parts.append(f"<p class='warn'>warning: {html.escape(warning)}</p>")
    model = (document.get("processing") or {}).get("model") or {}
    if model.get("tone_curve"):
        fig = tone_figure(model)
        parts.append("<h2>The processing fitted to the edges</h2>"
                     f"<img alt='tone curve and sharpening' src='data:image/png;base64,{_png(fig)}'>")
        plt.close(fig)
    buf = io.BytesIO()
    plot_fit(result, buf, title=f"{title}: {result.code}", image_format="png")
    parts.append("<h2>Blur versus inverse distance</h2>")
    parts.append(f"<img alt='fit plot' src='data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}'>")

    blur, z, w = edge_values(table, result)
    images = [(im.file.name, im.setting) for im in stack.images] if stack is not None else []
    rows = image_rows(table, blur, z, w, images)
    parts.append("<h2>Images</h2><div class='scroll'><table><tr><th>image</th><th>setting</th><th>corners</th>"
                 "<th>reprojection RMS (px)</th><th>edges</th><th>measured</th><th>not measured: why</th>"
                 "<th>used</th><th>distance (mm)</th><th>RMS residual / sigma</th>"
                 f"<th>|residual| &gt; {SUSPICIOUS_SIGMAS:g} sigma</th><th>down-weighted</th>"
                 "<th>flags of measured edges</th></tr>")
    for r in rows:
        flag = " class='bad'" if r["suspicious"] > max(2, 0.1 * r["used"]) else ""
        anchor = html.escape(r["image"])
        name = f"<a href='#{anchor}'>{anchor}</a>" if r["edges"] else anchor
        dist = f"{r['distance_mm'][0]:.0f}-{r['distance_mm'][1]:.0f}" if r["distance_mm"] else ""
        rms = "" if math.isnan(r["reprojection_rms_px"]) else f"{r['reprojection_rms_px']:.2g}"
        resid = "" if math.isnan(r["rms_residual_sigma"]) else f"{r['rms_residual_sigma']:.2f}"
        why = html.escape(r["why_none"] or r["not_measured"])
        none_class = " class='text bad'" if r["why_none"] else " class='text'"
        parts.append(f"<tr><td>{name}</td><td>{html.escape(r['setting'])}</td><td>{r['corners']}</td><td>{rms}</td>"
                     f"<td>{r['edges']}</td><td>{r['measured']}</td><td{none_class}>"
                     f"{why}</td><td>{r['used']}</td><td>{dist}</td><td>{resid}</td><td{flag}>{r['suspicious']}</td>"
                     f"<td>{r['down_weighted']}</td><td class='text'>{html.escape(r['flags'])}</td></tr>")
    parts.append("</table></div>")
    if stack is not None:
        fig = pose_figure(table, result, stack.targets, dict(images))
        if fig is not None:
            parts.append("<h2>Where the boards were</h2>"
                         f"<img alt='board poses' src='data:image/png;base64,{_png(fig)}'>")
            plt.close(fig)
    groups = samples_by_image(table)
    if stack is not None:
        finite = blur[np.isfinite(blur)]
        blur_range = (0.0, float(np.percentile(finite, 99)) if finite.size else 1.0)
        by_name = {im.file.name: im.index for im in stack.images}
        for k, r in enumerate(rows):
            if r["image"] not in by_name or r["image"] not in groups:
                continue
            idx = groups[r["image"]]
            image = stack.read(by_name[r["image"]])
            fig = overlay_figure(image, r["image"], [table.samples[i] for i in idx], blur[idx], z[idx], w[idx],
                                 table.corners_px.get(r["image"], []), blur_range)
            parts.append(f"<h3 id='{html.escape(r['image'])}'>{html.escape(r['image'])} (setting "
                         f"{html.escape(r['setting'])})</h3><img alt='overlay' src='data:image/png;base64,{_png(fig)}'>")
            plt.close(fig)
            if progress:
                progress(k + 1, len(rows))
    else:
        parts.append("<p class='note'>No overlays: the samples were read from a file, not measured on images.</p>")
    parts.append("</body></html>")
    Path(path).write_text("\n".join(parts), encoding="utf-8")
