"""Pictures of a fit: blur diameter against inverse distance with the fitted V, and residuals.

Matplotlib with the Agg backend (no display needed); imported only when a plot is asked for.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lensfit.fitting import FitResult

#: A sample whose robust weight is below this counts as down-weighted, in the plots (hollow) and
#: the fit report's header and table alike.
DOWN_WEIGHTED = 0.5


def plot_fit(result: FitResult, path, *, title: str | None = None, image_format: str | None = None) -> None:
    """Write a PNG/SVG/PDF (by suffix, or ``image_format`` for a file object) of the samples,
    the fitted V per setting and residuals.

    Top: measured blur diameter (px, with 1-sigma bars) against inverse distance (1/m; where field
    curvature was fitted, each sample's moved to the axis); the fitted model for a fronto-parallel
    edge on the axis; the focus distance marked. Bottom: residuals in
    units of each sample's sigma, outliers (robust weight below 0.5) hollow.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    data = result.samples
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1.2]},
                                  layout="constrained")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    w_all = 1000.0 * data.w_mean
    lo, hi = float(w_all.min()), float(w_all.max())
    for k, label in enumerate(data.labels):
        col = colours[k % len(colours)]
        sel = data.setting == k
        w = 1000.0 * data.w_mean[sel]
        fc = result.settings[label].get("field_curvature_per_m")
        moved = fc is not None and fc.value is not None
        if moved:  # each sample where its blur puts it on the axis: 1/d - kappa tan^2(field angle)
            w = w - fc.value * np.nan_to_num(data.field2[sel])
        good = result.weights[sel] >= DOWN_WEIGHTED
        ax.errorbar(w[good], data.coc_px[sel][good], yerr=data.sigma_px[sel][good], fmt="o", ms=3, color=col,
                    alpha=0.7, lw=0.8, label=f"setting {label}: {int(sel.sum())} edges"
                    + (" (moved to the axis by the fitted field curvature)" if moved else ""))
        if (~good).any():
            ax.plot(w[~good], data.coc_px[sel][~good], "o", mfc="none", color=col, ms=5, label="down-weighted")
        est = result.settings[label]
        inv = est["inverse_focus_distance_per_m"]
        x0 = min(lo, inv.value if inv.value is not None else lo)
        x1 = max(hi, inv.value if inv.value is not None else hi)
        pad = 0.05 * (x1 - x0 or 1.0)
        grid = np.linspace(max(x0 - pad, 1e-6), x1 + pad, 400)
        if inv.value is not None:
            # In the samples' frame: pose distances carry the calibration's scale (fit notes).
            c = result.predict_px(label, 1000.0 / grid, pose=bool(data.pose[sel].any()))
            text = _describe(result, label)
            ax.plot(grid, c, "-", color=col, lw=1.5, label=text)
            ax.axvline(grid[int(np.argmin(c))], color=col, ls=":", lw=1)
        axr.plot(w[good], result.residuals_px[sel][good] / data.sigma_px[sel][good], "o", ms=3, color=col, alpha=0.7)
        if (~good).any():
            axr.plot(w[~good], result.residuals_px[sel][~good] / data.sigma_px[sel][~good], "o", mfc="none",
                     color=col, ms=5)
    ax.set_ylabel("blur-disk diameter (px)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title or f"Blur versus inverse distance: fit {result.code}")
    ax.grid(alpha=0.3)
    axr.axhline(0, color="k", lw=0.8)
    axr.set_ylabel("residual / sigma")
    axr.set_xlabel("inverse distance from the lens (1/m)")
    axr.grid(alpha=0.3)
    if isinstance(path, (str, Path)):
        fig.savefig(path, dpi=110, metadata=creator(path))
    else:
        fig.savefig(path, dpi=110, format=image_format or "png")
    plt.close(fig)


def creator(path: str | Path) -> dict[str, str]:
    """Matplotlib metadata naming lensfit as the writer (``lensfit.outputs.writers.written_by`` reads it)."""
    from lensfit.outputs.writers import software_tag

    key = {".png": "Software", ".svg": "Title", ".pdf": "Creator"}.get(Path(path).suffix.lower())
    return {key: software_tag("lensfit")} if key else {}


def save_page(fig, path: str | Path, *, title: str, description: str | None = None, program: str = "lensfit",
              dpi: float | None = None) -> None:
    """Save a printable page by ``path``'s suffix (PDF, SVG or PNG): ``program`` named as its
    writer where ``lensfit.outputs.writers.written_by`` looks, ``title`` and ``description`` in its
    metadata, fonts embedded (PDF) or drawn as paths (SVG), and no date: the same page, the
    same file."""
    import matplotlib

    from lensfit.outputs.writers import software_tag

    kind = Path(path).suffix.lower()
    tag = software_tag(program)
    meta = {".pdf": {"Title": title, "Creator": tag, "CreationDate": None},
            ".svg": {"Title": title, "Creator": tag, "Date": None},
            ".png": {"Title": title, "Software": tag}}[kind]
    if description is not None:
        meta[{".pdf": "Subject", ".svg": "Description", ".png": "Description"}[kind]] = description
    with matplotlib.rc_context({"pdf.fonttype": 42, "svg.hashsalt": "lensfit", "svg.fonttype": "path"}):
        fig.savefig(path, format=kind[1:], metadata=meta, **({"dpi": dpi} if dpi else {}))


def _describe(result: FitResult, label: str) -> str:
    est = result.settings[label]
    return (f"fit: f {est['focal_length_mm'].text(' mm')}, N {est['f_number'].text()}, "
            f"focus {est['focus_distance_mm'].text(' mm')}")
