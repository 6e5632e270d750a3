"""Photographs developed by raw developers the project does not contain (``lensfit
bench-developed``): what a user who hands lensfit JPEGs gets.

synth renders the camera-raw scene (data_specs/scenes/camera_raw.toml: Bayer DNGs with black and
white levels, shot and read noise, diffraction, the camera's EXIF) at each f-number asked for
(:data:`F_NUMBERS`). Each developer found on the
machine develops the DNGs with its default profile into JPEGs, as a photographer exporting
"as shot" would: RawTherapee (``rawtherapee-cli -d``: its default processing profile) and
darktable (``darktable-cli``: its defaults for a new image). The JPEGs alone are copied into a
folder; ``lensfit init`` drafts its stack.toml from their EXIF (the board's entry from the
rendered stack) and ``lensfit fit`` fits it, each a fresh process as a user runs them. The DNGs
fitted as they are are the control; the drafted stacks are given the control's ``[lens]`` table
(an ideal lens: :func:`declare_lens`), so that they differ from it in their processing alone.
More cases show what the pixels alone tell: darktable's JPEGs without their Software tag, and a
camera-like pipeline written here (an S curve and an unsharp mask over sRGB, 4:2:0 JPEG, no EXIF),
once as it is and once with noise reduction before the mask (which the processing model does not
represent: N is to be refused naming it, or right). The record counts, over the developed stacks,
the 95 % intervals that hold the truth (:func:`coverage`).

A developer that is not installed is reported as missing with the package that provides it
(Debian: ``apt install rawtherapee darktable``). A case passes where f and the focus distance
are within 0.5 % and inside their 95 % intervals, and the f-number is within 1.5 % and inside
its interval, or refused naming the processing; the control, where all three are within 0.5 %.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from lensfit.io.specs import specs_dir

QUANTITIES = ("focal_length_mm", "f_number", "focus_distance_mm")
#: Developers: (program, Debian package); how each is run: :func:`_develop`.
DEVELOPERS = {
    "rawtherapee": ("rawtherapee-cli", "rawtherapee"),
    "darktable": ("darktable-cli", "darktable"),
}
#: Relative error allowed per quantity (f, N, focus distance) for a developed stack.
TOLERANCE = {"focal_length_mm": 0.005, "f_number": 0.015, "focus_distance_mm": 0.005}
CONTROL_TOLERANCE = 0.005


def _develop(name: str, program: str, dngs: list[Path], out: Path, scratch: Path) -> None:
    """JPEGs of ``dngs`` in ``out`` by developer ``name`` with its default processing."""
    out.mkdir(parents=True)
    if name == "rawtherapee":
        subprocess.run([program, "-o", str(out), "-d", "-j90", "-Y", "-c", *map(str, dngs)], check=True,
                       capture_output=True, timeout=1800)
    else:  # darktable: one call per image, a configuration and library of its own (never the user's)
        for dng in dngs:
            subprocess.run([program, str(dng), str(out / f"{dng.stem}.jpg"), "--core", "--configdir",
                            str(scratch / "darktable-config"), "--library", ":memory:"], check=True,
                           capture_output=True, timeout=600)
    for sidecar in list(out.glob("*.pp3")) + list(out.glob("*.xmp")):
        sidecar.unlink()


#: The camera pipeline of ``in-camera``: LibRaw's demosaic and sRGB encoding (rawpy), an S curve
#: (half a smoothstep), an unsharp mask (Gaussian sigma 1 px, amount 0.8) on the encoded values,
#: 4:2:0 JPEG at quality 90, no EXIF: what a camera's JPEG engine does, with nothing saying so.
S_CURVE, USM_SIGMA_PX, USM_AMOUNT = 0.5, 1.0, 0.8


def in_camera(dngs: list[Path], out: Path, usm_sigma_px: float = USM_SIGMA_PX,
              usm_amount: float = USM_AMOUNT, denoise_h: float = 0.0) -> None:
    """JPEGs of ``dngs`` in ``out`` through the pipeline of ``S_CURVE`` and an unsharp mask of
    ``usm_sigma_px``, ``usm_amount`` (by default ``USM_SIGMA_PX``, ``USM_AMOUNT``), with non-local
    means noise reduction of strength ``denoise_h`` (8-bit scale; 0: none) before the mask."""
    import cv2
    import numpy as np
    import rawpy
    from PIL import Image

    out.mkdir(parents=True)
    for dng in dngs:
        with rawpy.imread(str(dng)) as raw:
            rgb = raw.postprocess(use_camera_wb=True, no_auto_bright=True, output_bps=16, user_flip=0)
        x = rgb.astype(np.float64) / 65535.0
        x = (1 - S_CURVE) * x + S_CURVE * (3 * x**2 - 2 * x**3)
        if denoise_h > 0:
            x8 = np.clip(np.rint(255 * x), 0, 255).astype(np.uint8)
            x = cv2.fastNlMeansDenoisingColored(x8, None, denoise_h, denoise_h, 7, 21).astype(np.float64) / 255.0
        x = x + usm_amount * (x - cv2.GaussianBlur(x, (0, 0), usm_sigma_px))
        Image.fromarray(np.clip(np.rint(255 * x), 0, 255).astype(np.uint8)).save(
            out / f"{dng.stem}.jpg", "JPEG", quality=90, subsampling=2)


def without_software(src: Path, dst: Path) -> None:
    """The JPEGs of ``src`` with the EXIF Software tag removed (saved again with their own
    quantisation tables: the pixels change by the re-encoding only)."""
    from PIL import Image

    dst.mkdir(parents=True)
    for jpeg in sorted(src.glob("*.jpg")):
        with Image.open(jpeg) as im:
            exif = im.getexif()
            exif.pop(0x0131, None)
            im.save(dst / jpeg.name, "JPEG", quality="keep", exif=exif)


def declare_lens(control: Path, drafted: Path) -> None:
    """Give the drafted stack.toml the control's ``[lens]`` table (an ideal lens, unit focusing,
    P = 1), as the photographer who rendered the scene knows it: the DNG control and the developed
    stacks then differ in their processing alone, which is what the suite measures. (Undeclared,
    the f-number reported is the nominal one of a real design, ``lensfit.fitting.nominal``, about
    1.2 % below a thin lens's, and P's prior widens every interval.)"""
    import tomllib

    lens = tomllib.loads(control.read_text()).get("lens", {})
    if not lens:
        return
    lines = ["", "[lens]"] + [f"{k} = {json.dumps(v)}" for k, v in lens.items()]
    with drafted.open("a") as out:
        out.write("\n".join(lines) + "\n")


def _lensfit(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lensfit", *argv], capture_output=True, text=True, timeout=3600)


def _compare(results: dict[str, Any]) -> dict[str, Any]:
    """Per quantity of the (one) setting, from the fit's own comparison with the folder's
    truth.json (``truth_comparison``): the relative error and whether the 95 % interval holds the
    truth, or the refusal's reason."""
    rows = {r["quantity"]: r for r in results["truth_comparison"]}
    setting = next(iter(results["settings"].values()))
    return {q: ({"refused": True, "reason": setting[q].get("reason")} if rows[q]["estimate"] is None else
                {"refused": False, "relative_error": rows[q]["relative_error"], "inside": bool(rows[q]["within_ci95"])})
            for q in QUANTITIES}


def row_passed(errors: dict[str, Any], processing: dict[str, Any] | None, control: bool) -> bool:
    for q in QUANTITIES:
        e = errors[q]
        if e["refused"]:
            named = bool(processing and (processing.get("developer") or processing.get("halos")
                                         or processing.get("tone_mismatch")))
            if control or q != "f_number" or not named:
                return False
        elif abs(e["relative_error"]) > (CONTROL_TOLERANCE if control else TOLERANCE[q]) or not e["inside"]:
            return False
    return True


def program_for(name: str, tool: tuple[str, str], root: Path) -> str | None:
    """The program that develops case ``name`` (``""``: written here, nothing to install), or
    None where it is not installed or, for darktable's variant, darktable's JPEGs were not made."""
    if name.startswith("darktable,") and not (root / "darktable" / "photos").is_dir():
        return None
    return shutil.which(tool[0]) if tool[0] else ""


#: The f-numbers the camera-raw scene is rendered at (its own, f/11, and two stops wider: twice the
#: blur, more edges near the window's reach), the exposure time scaled to keep the light on the sensor.
F_NUMBERS = (11.0, 5.6)
#: Noise reduction of the in-camera case that applies it: non-local means (OpenCV's, strength h on
#: the 8-bit scale), as a camera's JPEG engine smooths before it sharpens.
DENOISE_H = 4.0


def scene_at(f_number: float) -> Any:
    """The camera-raw scene at ``f_number``, its exposure time scaled by the square of the stops so
    that the sensor gets the same light (nothing clips, the noise stays as it was)."""
    import tomllib

    from synth.scene import scene_from_dict

    path = specs_dir() / "scenes" / "camera_raw.toml"
    data = tomllib.loads(path.read_text())
    ratio = f_number / float(data["lens"]["f_number"])
    data["lens"]["f_number"] = float(f_number)
    data["exposure"]["shutter_s"] = float(data["exposure"]["shutter_s"]) * ratio**2
    return scene_from_dict(data, path)


def cases(developers: tuple[str, ...]) -> list[tuple[str, tuple[str, str] | None]]:
    """The stacks fitted at each f-number: (name, (program, Debian package)); None: the control,
    ("", ""): written here."""
    out: list[tuple[str, tuple[str, str] | None]] = [("DNG (control)", None)]
    out += [(name, DEVELOPERS[name]) for name in developers]
    if "darktable" in developers:  # its JPEGs again without the Software tag: what the pixels alone tell
        out.append(("darktable, Software tag removed", DEVELOPERS["darktable"]))
    out.append(("in-camera pipeline, no EXIF", ("", "")))
    out.append(("in-camera pipeline with noise reduction, no EXIF", ("", "")))
    return out


def _make(name: str, program: str, dngs: list[Path], root: Path, scratch: Path) -> Path:
    """The developed photos of case ``name`` in a new folder under ``root``."""
    if name.startswith("in-camera"):
        folder = root / ("in-camera-nr" if "noise" in name else "in-camera") / "photos"
        in_camera(dngs, folder, denoise_h=DENOISE_H if "noise" in name else 0.0)
    elif name.startswith("darktable,"):
        folder = root / "darktable" / "photos-variant"
        without_software(root / "darktable" / "photos", folder)
    else:
        folder = root / name / "photos"
        _develop(name, program, dngs, folder, scratch)
    return folder


def _draft(folder: Path, dng: Path, truth: dict[str, Any], row: dict[str, Any]) -> bool:
    """``lensfit init`` on ``folder`` (the pitch given where the developer dropped it), the control's
    lens declared and the truth copied beside the photos; False (``row["error"]`` says why) where
    init failed."""
    made = _lensfit("init", str(folder), "--target", str(dng / "stack.toml"))
    if made.returncode != 0 and "--pixel-pitch" in made.stderr:
        # the developer dropped the EXIF's focal-plane resolution: a user gives the pitch
        row["pixel_pitch_given"] = True
        made = _lensfit("init", str(folder), "--target", str(dng / "stack.toml"),
                        "--pixel-pitch", str(truth["pixel_pitch_mm"]))
    if made.returncode != 0:
        row["error"] = (made.stderr.strip().splitlines() or ["lensfit init failed"])[-1]
        return False
    declare_lens(dng / "stack.toml", folder / "stack.toml")
    # (the truth beside the photos: lensfit fit compares with it in results.json, never reads it otherwise)
    shutil.copy(dng / "truth.json", folder / "truth.json")
    return True


def run(progress: Callable[[str], None] = lambda m: None, developers: tuple[str, ...] = tuple(DEVELOPERS),
        keep: Path | None = None, f_numbers: tuple[float, ...] = F_NUMBERS) -> dict[str, Any]:
    """Render at each of ``f_numbers``, develop, fit and compare (see the module notes); ``keep``: a
    new folder to keep the stacks in (default: a scratch folder removed afterwards)."""
    from synth import render, write_stack

    rows, truths = [], {}
    with tempfile.TemporaryDirectory(prefix="lensfit-developed-") as tmp:
        base = Path(keep) if keep is not None else Path(tmp) / "work"
        for f_number in f_numbers:
            root = base / f"f{f_number:g}"
            progress(f"rendering the camera-raw scene at f/{f_number:g} (DNG)")
            write_stack(render(scene_at(f_number)), root / "dng")
            truth = json.loads((root / "dng" / "truth.json").read_text())
            truths[f"{f_number:g}"] = {"focal_length_mm": truth["focal_length_mm"],
                                       **next(iter(truth["settings"].values()))}
            dngs = sorted((root / "dng").glob("*.dng"))
            for name, tool in cases(developers):
                row: dict[str, Any] = {"stack": name, "f_number": f_number}
                folder = root / "dng"
                if tool is not None:
                    program = program_for(name, tool, root)
                    if program is None:
                        rows.append({**row, "missing": f"{tool[0]} not found: install it (Debian: apt install {tool[1]})"})
                        continue
                    progress(f"f/{f_number:g}: developing with {name}")
                    t = time.perf_counter()
                    folder = _make(name, program, dngs, root, Path(tmp))
                    row["seconds_develop"] = time.perf_counter() - t
                    row["photos"] = len(list(folder.glob("*.jpg")))
                    if not _draft(folder, root / "dng", truth, row):
                        rows.append(row)
                        continue
                progress(f"f/{f_number:g}: fitting {name}")
                rows.append(_fitted(row, folder, root / f"{len(rows)}-results.json", control=tool is None))
    ran = [r for r in rows if "missing" not in r]
    from lensfit.bench.records import record_header

    return {**record_header("developed", "lensfit bench-developed"), "truth": truths,
            "rows": rows, "coverage": coverage(rows), "passed": sum(bool(r.get("passed")) for r in ran),
            "total": len(ran)}


def _fitted(row: dict[str, Any], folder: Path, out: Path, control: bool) -> dict[str, Any]:
    """``row`` with the fit of ``folder`` compared with its truth."""
    t = time.perf_counter()
    fitted = _lensfit("fit", str(folder), "--out", str(out), "--force")
    row["seconds_fit"] = time.perf_counter() - t
    row["exit"] = fitted.returncode
    if not out.is_file():
        row["error"] = (fitted.stderr.strip().splitlines() or ["lensfit fit failed"])[-1]
        return row
    results = json.loads(out.read_text())
    row["errors"] = _compare(results)
    row["processing"] = results.get("processing")
    row["chi2_reduced"] = results.get("diagnostics", {}).get("chi2_reduced")
    row["passed"] = row_passed(row["errors"], row["processing"], control=control)
    return row


def coverage(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per quantity over the developed stacks (not the controls): intervals that hold the truth of
    those reported, with Wilson's 95 % interval, and the refusals apart."""
    from lensfit.bench.coverage import wilson_interval

    out = {}
    for q in QUANTITIES:
        got = [r["errors"][q] for r in rows if "errors" in r and not r["stack"].startswith("DNG")]
        shown = [e for e in got if not e["refused"]]
        held = sum(bool(e["inside"]) for e in shown)
        out[q] = {"held": held, "reported": len(shown), "refused": len(got) - len(shown),
                  "wilson95": wilson_interval(held, len(shown)) if shown else None,
                  "mean_abs_error": (sum(abs(e["relative_error"]) for e in shown) / len(shown)) if shown else None}
    return out


def _cell(e: dict[str, Any] | None) -> str:
    if e is None:
        return ""
    if e["refused"]:
        return "refused"
    return f"{100 * e['relative_error']:+.2f} %" + ("" if e["inside"] else " (outside)")


def markdown(doc: dict[str, Any]) -> str:
    """The record as the documentation's table."""
    out = [f"### Developed photographs ({doc['passed']} of {doc['total']} pass)", "",
           f"`{doc['command']}`, {doc['date']}, {doc['system']}. The camera-raw scene's DNGs (25 mm, focused at 1 m) "
           "developed with each program's default profile into JPEGs, drafted by `lensfit init` and fitted; the DNGs "
           "themselves are the control. A developed stack passes with f and the focus distance within 0.5 % and "
           "inside their 95 % intervals and the f-number within 1.5 % or refused naming the processing.", "",
           "| f-number | stack | f | N | focus distance | processing named | reduced chi-square | pass |",
           "|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        stop = f"f/{r['f_number']:g}" if r.get("f_number") else ""
        if r.get("pixel_pitch_given"):
            r = dict(r, stack=f"{r['stack']} (pixel pitch given: the EXIF lost it)")
        if "missing" in r or "error" in r:
            passed = "no" if "error" in r else "-"
            out.append(f"| {stop} | {r['stack']} | {r.get('missing') or r.get('error')} | | | | | {passed} |")
            continue
        e, proc = r["errors"], r.get("processing") or {}
        named = "; ".join(filter(None, (proc.get("developer"), "sharpening halos" if proc.get("halos") else "",
                                        f"tone curve ({proc['tone_offset']:+.3f} of a radius)"
                                        if proc.get("tone_mismatch") else "")))
        chi2 = "" if r.get("chi2_reduced") is None else f"{r['chi2_reduced']:.2f}"
        out.append(f"| {stop} | {r['stack']} | {_cell(e['focal_length_mm'])} | {_cell(e['f_number'])} | "
                   f"{_cell(e['focus_distance_mm'])} | {named} | {chi2} | {'yes' if r['passed'] else '**no**'} |")
    cover = doc.get("coverage")
    if cover:
        parts = []
        for q, label in zip(QUANTITIES, ("f", "N", "focus distance")):
            c = cover[q]
            if c["reported"]:
                lo, hi = c["wilson95"]
                parts.append(f"{label} {c['held']} of {c['reported']} ({100 * lo:.0f}-{100 * hi:.0f} %"
                             + (f"; {c['refused']} refused)" if c["refused"] else ")"))
        out += ["", "95 % intervals that hold the truth over the developed stacks (Wilson's 95 % interval): "
                + ", ".join(parts) + "."]
    return "\n".join(out)
