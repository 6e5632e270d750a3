"""The price of accuracy: render error against seconds for synth's two methods on one shot of
the demo scene. The reference is the convolution renderer at 8 x 8 sub-pixels (exact for a
fronto-parallel board, and equal to 4096-spp ray tracing within the tracer's own noise).

Run from the repository root: ``python docs/examples/price_of_accuracy.py [OUT]`` (default
``out/examples/price_of_accuracy``). The figure is ``OUT/price_of_accuracy.png``.
"""

import sys
import time
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from synth.convolve import render_convolve
from synth.raytrace import render_raytrace
from synth.scene import load_scene

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/price_of_accuracy")
out.mkdir(parents=True, exist_ok=True)

scene = load_scene("data_specs/scenes/demo.toml")
shot = next(s for s in scene.shots if all(o.pose.fronto_parallel for o in s.objects))
background = scene.background_value
reference = render_convolve(shot, background, 8).astype(np.float64)


def timed(render):
    render()                                     # the first call compiles: not part of the price
    start = time.perf_counter()
    image = render()
    return time.perf_counter() - start, float(np.sqrt(np.mean((image - reference) ** 2)))


rows = {"raytrace (spp)": [(spp, *timed(lambda: render_raytrace(shot, background, spp, seed=1)))
                           for spp in (4, 16, 64, 256)],
        "convolve (sub-pixels a side)": [(n, *timed(lambda: render_convolve(shot, background, n))) for n in (1, 2, 4)]}

fig, ax = plt.subplots(figsize=(6, 4), layout="constrained")
for (method, points), marker in zip(rows.items(), ("o-", "s-")):
    _, seconds, errors = zip(*points)
    ax.loglog(seconds, errors, marker, label=method)
    for setting, s, e in points:
        ax.annotate(str(setting), (s, e), textcoords="offset points", xytext=(4, 4))
        print(f"{method:30s} {setting:5d}: {s:7.3f} s, RMS error {e:.1e}")
ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())   # decades only: readable labels
ax.set_xlabel("seconds per 1-megapixel shot (warm)")
ax.set_ylabel("RMS error (linear intensity)")
ax.set_title("demo shot: error against time")
ax.legend()
fig.savefig(out / "price_of_accuracy.png", dpi=80)
