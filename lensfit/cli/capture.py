"""The capture commands: ``lensfit target`` (a printable board), ``init`` (stack.toml from the
photos' EXIF) and ``plan`` (target distances and shots for a requested accuracy)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from lensfit.errors import InputError
from lensfit.cli.common import EXIT_OK, CliError, fail_input, fmt_mm

_TARGET_OPTIONS = {"paper": "--paper", "squares": "--squares", "square_mm": "--square-mm",
                   "marker_mm": "--marker-mm", "dictionary": "--dictionary", "dpi": "--dpi"}


def target_command(args: argparse.Namespace) -> int:
    from lensfit.outputs.writers import claimed, write_all
    from lensfit.capture.printable import PAGE_SUFFIXES, charuco_page, target_toml, write_page
    from lensfit.capture.shotlist import CHECKLIST

    out = Path(args.out)
    if out.suffix.lower() not in PAGE_SUFFIXES:
        raise CliError(f"--out {out}: give a .pdf, .svg or .png file name")
    try:
        board = charuco_page(args.paper, tuple(args.squares), args.square_mm, args.marker_mm, args.dictionary,
                             args.dpi, args.id)
    except InputError as exc:
        raise fail_input(exc, _TARGET_OPTIONS) from None
    outputs = [("--out", out)] + ([("--entry", Path(args.entry))] if args.entry else [])
    if args.entry and Path(args.entry).suffix.lower() != ".toml":
        raise CliError(f"--entry {args.entry}: give a .toml file name (e.g. board.toml)")
    entry_text = (f"# Written by lensfit target: the [[target]] entry of stack.toml for {out.name} "
                  "(lensfit init --target reads it).\n" + target_toml(board.entry))
    with claimed(outputs, force=args.force):
        write_all([(out, lambda tmp: write_page(board, tmp))]
                  + ([(Path(args.entry), lambda tmp: tmp.write_text(entry_text))] if args.entry else []),
                  force=args.force)
    e = board.entry
    print(f"# {out}: {e['squares'][0]} x {e['squares'][1]} squares of {e['square_mm']:g} mm "
          f"({e['squares'][0] * e['square_mm']:g} x {e['squares'][1] * e['square_mm']:g} mm) on "
          f"{board.page_mm[0]:g} x {board.page_mm[1]:g} mm, "
          + ("vector." if out.suffix.lower() != ".png" else f"{board.dpi:.1f} dpi."))
    print("# Print at 100 % (actual size), mount it flat and measure a square (or the scale bar) with a ruler: "
          f"where a square is not {e['square_mm']:g} mm, give what you measured to lensfit init "
          "--measured-square-mm MM (printers scale by a few per cent; the focus distance scales with it).")
    print("# Then photograph it: " + "; ".join(CHECKLIST) + "; the board at 6 or more distances on both sides of "
          "the focus, some shots tilted 20-40 degrees (lensfit plan gives the distances and a shot list to print).")
    print("# stack.toml entry:")
    print(target_toml(e), end="")
    return EXIT_OK


# --------------------------------------------------------------------------- init

_INIT_OPTIONS = {"measured_square_mm": "--measured-square-mm", "pixel_pitch_mm": "--pixel-pitch",
                 "sensor_width_mm": "--sensor-width", "sensor": "--sensor",
                 "settings": "--settings", "prefer": "--prefer", "photos": "PHOTOS_DIR"}


def init_command(args: argparse.Namespace) -> int:
    from lensfit.io.manifest import draft_manifest, shown
    from lensfit.outputs.writers import claimed, write_text

    folder = Path(args.photos)
    out = Path(args.out) if args.out else folder / "stack.toml"
    if out.suffix.lower() != ".toml":
        raise CliError(f"--out {out}: give a .toml file name (lensfit reads stack.toml)")
    if not folder.is_dir():
        raise CliError(f"PHOTOS_DIR {folder}: no such folder; give the folder that holds the photos of the target")
    if out.parent.resolve() != folder.resolve():
        raise CliError(f"--out {out}: write it into {folder} (a manifest names its images relative to itself), "
                       f"e.g. --out {folder / 'stack-jpeg.toml'}")
    try:
        with claimed([("--out", out)], force=args.force):
            draft = draft_manifest(folder, target_file=args.target, pixel_pitch_mm=args.pixel_pitch,
                                   sensor=args.sensor, sensor_width_mm=args.sensor_width, grouping=args.settings,
                                   prefer=args.prefer, max_pixels=int(args.max_megapixels * 1e6),
                                   measured_square_mm=args.measured_square_mm)
            write_text(out, draft.text, force=args.force)
    except InputError as exc:
        raise fail_input(exc, _INIT_OPTIONS) from None
    print(f"wrote {out}: {len(draft.rows)} image(s), {len({r['setting'] for r in draft.rows})} setting(s)")
    print(f"{'file':<28} {'setting':>7} {'f (mm)':>8} {'N':>6} {'focus (mm)':>11}")
    for r in draft.rows:
        def show(x, spec):
            return "-" if x is None else ("inf" if math.isinf(x) else format(x, spec))
        print(f"{shown(r['file'])[:28]:<28} {r['setting']:>7} {show(r['focal_length_mm'], '8.4g'):>8} "
              f"{show(r['f_number'], '6.3g'):>6} {show(r['focus_distance_mm'], '11.5g'):>11}")
    for note in draft.notes:
        print(f"note: {shown(note)}")
    dest = out.parent if out.name == "stack.toml" else out
    print(f"next: check the setting labels and the target in {out}, then: lensfit fit {dest}")
    return EXIT_OK


# --------------------------------------------------------------------------- plan

_PLAN_OPTIONS = {"focal_length_mm": "--focal-length", "f_number": "--f-number", "focus_distance_mm": "--focus-distance",
                 "pixel_pitch_mm": "--pixel-pitch", "goal": "--goal", "max_shots": "--max-shots",
                 "width_px": "--width-px", "target": "--target", "target.kind": "--target's kind"}


def plan_command(args: argparse.Namespace) -> int:
    from lensfit.capture.plan import QUANTITIES, Board, blur_at, plan_capture
    from lensfit.io.sensors import sensor_format

    try:
        if args.sensor:
            fmt = sensor_format(args.sensor)
            width_px, height_px = args.width_px, args.height_px
            if fmt.resolution_px and width_px is None:
                width_px, height_px = fmt.resolution_px
            if width_px is None or height_px is None:
                raise CliError(f"--sensor {args.sensor} has no pixel grid in data_specs/sensor_formats.toml; "
                               "give --width-px and --height-px")
            pitch = args.pixel_pitch or fmt.width_mm / width_px
        else:
            if args.pixel_pitch is None or args.width_px is None or args.height_px is None:
                raise CliError("give --sensor NAME, or --pixel-pitch MM with --width-px and --height-px")
            pitch, width_px, height_px = args.pixel_pitch, args.width_px, args.height_px
        from lensfit.io.manifest import target_entries

        entries, _ = target_entries(Path(args.target) if args.target else None)
        board = Board.from_entry(entries[0])
        plan = plan_capture(args.focal_length, args.f_number, args.focus_distance, pixel_pitch_mm=pitch,
                            width_px=int(width_px), height_px=int(height_px), board=board, goal_rel=args.goal / 100,
                            max_shots=args.max_shots, edge_sigma_px=args.edge_sigma_px,
                            edge_sigma_rel=args.edge_sigma_rel / 100,
                            calibration_sigma_rel=args.calibration_sigma / 100)
    except InputError as exc:
        raise fail_input(exc, _PLAN_OPTIONS) from None
    if args.shot_list:
        _write_shot_list(args, plan, board, pitch, width_px, height_px)
    if args.json:
        print(json.dumps(plan.to_json_dict(), indent=1))
        return EXIT_OK
    print(f"lens guess f {args.focal_length:g} mm, f/{args.f_number:g}, focus {fmt_mm(args.focus_distance)}; "
          f"board {board.width_mm:g} x {board.height_mm:g} mm ({board.edges} edges per shot); sensor "
          f"{width_px} x {height_px} px of {pitch * 1000:.3g} um")
    print(f"usable target distances: {plan.usable_mm[0]:.0f} to {plan.usable_mm[1]:.0f} mm from the lens")
    if plan.shots is not None:
        print(f"{plan.shots} shots reach 95 % intervals within {args.goal:g} % on f, N and focus distance:")
    else:
        print(f"closest plan ({len(plan.distances_mm)} shots); the goal of {args.goal:g} % is not reached:")
    print(f"{'shot':>5} {'distance (mm)':>14} {'blur (px)':>10}")
    for k, d in enumerate(plan.distances_mm):
        print(f"{k + 1:>5} {d:>14.0f} {blur_at(args.focal_length, args.f_number, args.focus_distance, d, pitch):>10.2f}")
    print("predicted 95 % half-interval (Cramer-Rao bound, fronto-parallel shots): " + ", ".join(
        f"{q} {100 * 1.96 * plan.sigma[q]:.2g} %" for q in QUANTITIES if math.isfinite(plan.sigma[q])))
    print("what accuracy costs in capture (shots -> 95 % half-interval of f, N, focus distance):")
    for row in plan.curve:
        if row["shots"] in (3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96) or row["shots"] == plan.shots:
            at = (" at " + ", ".join(f"{d:.0f}" for d in row["distances_mm"]) + " mm") if row["shots"] <= 12 else ""
            print(f"  {row['shots']:>3} shots: " + ", ".join(
                f"{100 * 1.96 * row[q]:.2g} %" if math.isfinite(row[q]) else "-" for q in QUANTITIES) + at)
    for note in plan.notes:
        print(f"note: {note}")
    print("note: a lower bound for an unbiased fit; tilt some shots by 20-40 degrees for the calibration")
    return EXIT_OK


def _write_shot_list(args: argparse.Namespace, plan, board, pitch: float, width_px: int, height_px: int) -> None:
    from lensfit.outputs.writers import claimed, write_all
    from lensfit.capture.plan import blur_at
    from lensfit.capture.shotlist import promise_text, shot_rows, write_shot_list

    out = Path(args.shot_list)
    if out.suffix.lower() not in (".pdf", ".svg", ".png"):
        raise CliError(f"--shot-list {out}: give a .pdf, .svg or .png file name")
    rows = shot_rows(plan.distances_mm, [blur_at(args.focal_length, args.f_number, args.focus_distance, d, pitch)
                                         for d in plan.distances_mm])
    lines = [f"Lens: {args.focal_length:g} mm at f/{args.f_number:g}, focused at {fmt_mm(args.focus_distance)} "
             "(set once, then leave it).",
             f"Board: {board.width_mm:g} x {board.height_mm:g} mm, squares of {board.square_mm:g} mm; sensor "
             f"{width_px} x {height_px} px of {pitch * 1000:.3g} um.",
             f"Usable distances {plan.usable_mm[0]:.0f} to {plan.usable_mm[1]:.0f} mm from the lens; the board "
             "in the middle of the frame."] + [f"Note: {note}" for note in plan.notes]
    title = f"lensfit shot list: {len(rows)} shots"
    promise = promise_text(plan.sigma, args.goal, plan.shots is not None)
    with claimed([("--shot-list", out)], force=args.force):
        write_all([(out, lambda tmp: write_shot_list(tmp, title, lines, rows, promise))], force=args.force)
    print(f"wrote the shot list {out}", file=sys.stderr if args.json else sys.stdout)  # --json: stdout is JSON
