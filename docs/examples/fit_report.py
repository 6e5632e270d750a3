"""A fit and its report: render the demo stack, measure and fit it as `lensfit fit` does, draw
the fitted blur "V" and write the HTML report.

Run from the repository root: ``python docs/examples/fit_report.py [OUT]`` (default
``out/examples/fit_report``). The figure is ``OUT/fit_report.png``.
"""

import json
import sys
from pathlib import Path

import synth
from lensfit.fitting import results_document
from lensfit.outputs.report import write_fit_report
from lensfit.measurement.pipeline import measure_and_fit
from lensfit.outputs.plots import plot_fit
from lensfit.io.stack import load_stack

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/fit_report")
out.mkdir(parents=True, exist_ok=True)

# 16 samples per pixel instead of the scene's 64: a quicker render, a little more noise
stack = synth.render("data_specs/scenes/demo.toml", samples_per_pixel=16, seed=1)
synth.write_stack(stack, out / "stack", force=True)

# what `lensfit fit` runs: measure, fit, and model diffraction where the edges show it
samples, result, rounds = measure_and_fit(out / "stack", auto_diffraction=True)
plot_fit(result, out / "fit_report.png", title="demo stack: blur against inverse distance")

truth = json.loads((out / "stack" / "truth.json").read_text())
print(f"fit: {result.code}, {result.n_samples} edges fitted, {result.n_outliers} down-weighted")
for name, estimate, true in [("focal length (mm)", result.focal_length_mm, truth["focal_length_mm"]),
                             ("f-number", result.settings["a"]["f_number"], truth["settings"]["a"]["f_number"]),
                             ("focus distance (mm)", result.settings["a"]["focus_distance_mm"],
                              truth["settings"]["a"]["focus_distance_mm"])]:
    lo, hi = estimate.ci95
    print(f"{name:20s} {estimate.value:10.4f} +- {estimate.sigma:.4f}  95 %: [{lo:.4f}, {hi:.4f}]  "
          f"truth {true:g} ({100 * (estimate.value / true - 1):+.3f} %)")
print("variance of N from:", {k: round(v, 3) for k, v in result.settings["a"]["f_number"].shares.items()})

# the HTML report: every image with its edges coloured by residual, as `lensfit fit --report` writes it
document = results_document(result, None, truth, intrinsics=samples.intrinsics)
write_fit_report(out / "report.html", result, document, samples, load_stack(out / "stack"))
print("report:", out / "report.html")
