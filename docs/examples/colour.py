"""Colour: a thin lens with longitudinal and lateral chromatic aberration, rendered in red, green
and blue. Off the axis each channel lands at its own magnification, so edges show coloured
fringes; each channel also focuses at its own distance, so its blur differs.

Run from the repository root: ``python docs/examples/colour.py [OUT]`` (default
``out/examples/colour``). The figure is ``OUT/colour.png``.
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import synth
from synth.preview import linear_to_srgb

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/colour")
out.mkdir(parents=True, exist_ok=True)

stack = synth.render("data_specs/scenes/colour.toml")
synth.write_stack(stack, out / "stack", force=True)
image = stack.images["shot_001.png"]                     # the board off the axis, (H, W, 3) linear
aberration = stack.truth["images"][1]["chromatic_aberration"]
for name, D in zip(aberration["channels"], aberration["channel_focus_distance_mm"]):
    print(f"{name:5s} channel in focus at {D:7.1f} mm")

# the board's corner farthest from the frame's centre, and a row through the square beside it
height, width = image.shape[:2]
corners = np.asarray(stack.truth["images"][1]["targets"][0]["corners_px"], dtype=float).reshape(-1, 2)
x0, y0 = corners[np.argmax(np.hypot(corners[:, 0] - width / 2, corners[:, 1] - height / 2))]
row = int(round(y0 - np.sign(y0 - height / 2) * 20))
xs = np.arange(int(x0) - 20, int(x0) + 21)

fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
left.imshow(linear_to_srgb(np.clip(image, 0, 1)))
left.plot(xs, np.full(xs.shape, row), "r-", lw=2)
left.set_title("shot_001: the board off the axis (sRGB)")
left.axis("off")
for channel, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
    right.plot(xs - x0, image[row, xs, channel], color=colour, label=("red", "green", "blue")[channel])
right.set_xlabel("pixels from the corner's column")
right.set_ylabel("linear intensity")
right.set_title("along the red line: each channel shifted and blurred")
right.legend()
fig.savefig(out / "colour.png", dpi=80)
print("figure:", out / "colour.png")
