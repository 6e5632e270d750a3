"""A compound lens: render through the Cooke triplet (six spherical surfaces, EFL 50 mm) at f/8
instead of a thin lens, and read what the truth records of a real lens: its paraxial focal
length, pupil magnification and real-ray f-number, which differ from the nominal ones.

Run from the repository root: ``python docs/examples/compound_lens.py [OUT]`` (default
``out/examples/compound_lens``). The figure is ``OUT/compound_lens.png``.
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import synth
from synth.preview import linear_to_srgb

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/compound_lens")
out.mkdir(parents=True, exist_ok=True)

stack = synth.render("data_specs/scenes/compound_lens.toml")
synth.write_stack(stack, out / "stack", force=True)
truth = stack.truth
setting = truth["settings"]["a"]
paraxial = setting["lens"]["paraxial"]
print(f"effective focal length   {truth['focal_length_mm']:.3f} mm (a thin lens's f)")
print(f"f-number                 {setting['f_number']:g} nominal (EFL / paraxial entrance pupil), "
      f"{setting['real_ray_f_number']:.3f} for the real rays from the focus distance")
print(f"pupil magnification P    {setting['pupil_magnification']:.4f} (exit / entrance pupil; 1 for a thin lens)")
print(f"focus distance           {setting['focus_distance_mm']:g} mm at best focus, from the entrance pupil; "
      f"the paraxial focus is at {setting['paraxial_focus_distance_mm']:.0f} mm (spherical aberration)")
print(f"pinhole distance S       {setting['pinhole_distance_mm']:.3f} mm (what a calibration measures)")

fig, axes = plt.subplots(1, len(stack.images), figsize=(4 * len(stack.images), 3), layout="constrained")
for ax, (name, image), target in zip(axes, sorted(stack.images.items()), truth["images"]):
    ax.imshow(linear_to_srgb(image), cmap="gray", vmin=0, vmax=1)
    board = target["targets"][0]
    ax.set_title(f"{name}: board at {board['distance_mm'] / 1000:.1f} m, CoC {board['coc_diameter_px']:.1f} px")
    ax.axis("off")
fig.suptitle("Cooke triplet at f/8 focused at 2 m: nearer, at and beyond the focus")
fig.savefig(out / "compound_lens.png", dpi=80)
