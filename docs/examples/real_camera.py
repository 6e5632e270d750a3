"""A real-camera round trip: print a board, photograph it, draft stack.toml from the photos'
EXIF, fit. synth takes the photographs (data_specs/scenes/printed_target.toml: the printed page
as an image texture, 8-bit sRGB JPEGs with the camera's EXIF); only the JPEGs are copied to the
photo folder, so `lensfit init` sees what a photographer has.

Run from the repository root: ``python docs/examples/real_camera.py [OUT]`` (default
``out/examples/real_camera``). The figure is ``OUT/real_camera.png``.
"""

import json
import shutil
import sys
import tomllib
from pathlib import Path

import synth
from lensfit.cli import main as lensfit

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/real_camera")
out.mkdir(parents=True, exist_ok=True)

# 1. the board as `lensfit target` prints it, and its [[target]] entry (the shipped scene's page
#    is this command's output)
lensfit(["target", "--out", str(out / "board.png"), "--dpi", "150", "--entry", str(out / "board.toml"), "--force"])

# 2. the photographs: seven JPEGs of the printed page at 0.7-2.2 m, some tilted
shots = synth.render("data_specs/scenes/printed_target.toml")
synth.write_stack(shots, out / "camera", force=True)
photos = out / "photos"
photos.mkdir(exist_ok=True)
for jpeg in sorted((out / "camera").glob("*.jpg")):
    shutil.copy(jpeg, photos / jpeg.name)

# 3. draft stack.toml from the EXIF: pixel pitch, one setting, the board (--force replaces only
#    a stack.toml that init wrote, from an earlier run)
assert lensfit(["init", str(photos), "--target", str(out / "board.toml"), "--force"]) == 0
manifest = tomllib.loads((photos / "stack.toml").read_text())
print("init read: pixel pitch", manifest["camera"]["pixel_pitch_mm"], "mm,", len(manifest["image"]), "photos, settings",
      sorted({image["setting"] for image in manifest["image"]}))

# 4. fit, with the plot and the report
code = lensfit(["fit", str(photos), "--out", str(out / "results.json"), "--plot", str(out / "real_camera.png"),
                "--report", str(out / "report.html"), "--force"])
results = json.loads((out / "results.json").read_text())
truth = json.loads((out / "camera" / "truth.json").read_text())
setting = next(iter(results["settings"].values()))
for name, got, true in [("focal length (mm)", results["focal_length_mm"], truth["focal_length_mm"]),
                        ("f-number", setting["f_number"], truth["settings"]["a"]["f_number"]),
                        ("focus distance (mm)", setting["focus_distance_mm"], truth["settings"]["a"]["focus_distance_mm"])]:
    lo, hi = got["ci95"]
    print(f"{name:20s} {got['value']:9.3f}  95 %: [{lo:.3f}, {hi:.3f}]  truth {true:g}  "
          f"({100 * (got['value'] / true - 1):+.2f} %)")
print("exit status", code, "; report:", out / "report.html")
