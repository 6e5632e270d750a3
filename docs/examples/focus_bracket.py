"""A focus bracket: two focus settings of one lens (0.7 m and 1.4 m at f/11), fitted jointly.
The settings share the focal length and the pupil magnification P; each has its own focus
distance. Two focus distances let the fit determine P, which one setting cannot.

Run from the repository root: ``python docs/examples/focus_bracket.py [OUT]`` (default
``out/examples/focus_bracket``). The figure is ``OUT/focus_bracket.png``.
"""

import json
import sys
from pathlib import Path

import synth
from lensfit.measurement.pipeline import measure_and_fit
from lensfit.outputs.plots import plot_fit

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/focus_bracket")
out.mkdir(parents=True, exist_ok=True)

stack = synth.render("data_specs/scenes/focus_bracket.toml", samples_per_pixel=16, seed=2)
synth.write_stack(stack, out / "stack", force=True)
samples, result, rounds = measure_and_fit(out / "stack", auto_diffraction=True)
plot_fit(result, out / "focus_bracket.png", title="focus bracket: one V per setting")

truth = json.loads((out / "stack" / "truth.json").read_text())
f = result.focal_length_mm
print(f"focal length {f.value:.3f} mm, 95 % [{f.ci95[0]:.3f}, {f.ci95[1]:.3f}] "
      f"(truth {truth['focal_length_mm']:g}: {100 * (f.value / truth['focal_length_mm'] - 1):+.3f} %)")
P = result.pupil_magnification
print(f"pupil magnification {P.value:.3f} +- {P.sigma:.3f} ({result.pupil_magnification_source}; a thin lens has 1)")
for label in result.settings:
    D = result.settings[label]["focus_distance_mm"]
    N = result.settings[label]["f_number"]
    true = truth["settings"][label]
    print(f"setting {label}: focus {D.value:7.1f} mm, 95 % [{D.ci95[0]:.1f}, {D.ci95[1]:.1f}] "
          f"(truth {true['focus_distance_mm']:g}: {100 * (D.value / true['focus_distance_mm'] - 1):+.3f} %); "
          f"N {N.value:.3f} +- {N.sigma:.3f} (truth {true['f_number']:g}: {100 * (N.value / true['f_number'] - 1):+.3f} %)")
