"""``lensfit measure`` and ``lensfit fit``: measure a stack, fit the lens, write and print."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from lensfit.errors import InputError
from lensfit.cli.common import (EXIT_NOT_IDENTIFIABLE, EXIT_OK, CliError, max_pixels_arg, progress_bar)

def _measure_with_progress(stack, args: argparse.Namespace, fit_options: dict | None = None):
    """``lensfit.measurement.measure.measure`` with a progress bar on stderr; with ``fit_options`` measure and
    fit (``lensfit.measurement.pipeline``: diffraction modelled where ``--diffraction`` asks) and return
    (samples, result, rounds)."""
    from rich.console import Console

    from lensfit.runtime.jaxcache import enable_compilation_cache
    from lensfit.measurement.measure import measure
    from lensfit.measurement.pipeline import measure_and_fit

    enable_compilation_cache()
    console = Console(stderr=True)
    with progress_bar(console, args.progress) as bar:
        task = bar.add_task("measuring", total=None)

        def progress(stage, done, total):
            bar.update(task, description=stage, completed=done, total=total)

        if fit_options is None:
            return measure(stack, args.estimator, progress=progress, jobs=args.jobs)
        mode = getattr(args, "diffraction", "off")
        return measure_and_fit(stack, args.estimator, wavelength_nm=mode if isinstance(mode, float) else None,
                               fit_options=fit_options, progress=progress, auto_diffraction=mode == "auto",
                               processed=getattr(args, "processed", "model"), jobs=args.jobs)


def measure_command(args: argparse.Namespace) -> int:
    from lensfit.estimators import ESTIMATORS
    from lensfit.io.stack import load_stack

    if args.estimator not in ESTIMATORS:
        raise CliError(f"--estimator must be one of {', '.join(ESTIMATORS)}, got {args.estimator!r}")
    from lensfit.outputs.writers import claimed, write_all

    out = Path(args.out)
    if out.suffix.lower() not in (".csv", ".json"):
        raise CliError(f"--out must end in .csv or .json, got {args.out!r}")
    with claimed([("--out", out)], force=args.force):
        stack = load_stack(args.stack, max_pixels=max_pixels_arg(args), allow_outside=args.allow_outside_stack)
        table = _measure_with_progress(stack, args)
        write_all([(out, table.write)], force=args.force)
    valid = table.valid()
    for w in table.warnings:
        print(f"warning: {w}", file=sys.stderr)
    intr = ", ".join(f"{k}: {v.focal_length_px:.2f} px ({v.views} views, rms {v.rms_px:.3f} px)"
                     for k, v in table.intrinsics.items())
    print(f"{len(valid)} of {len(table)} edges measured in {len(stack.images)} images with '{args.estimator}'; "
          f"focal length in px per setting: {intr}; wrote {out}")
    return EXIT_OK


def _write_fit_outputs(args, source: Path, table, result, document, stack=None) -> list[Path]:
    """Every output to a temporary sibling first, then renamed: all appear, or none."""
    from lensfit.fitting import write_results
    from lensfit.outputs.writers import write_all

    files = []
    if args.out:
        files.append((Path(args.out), lambda tmp: write_results(tmp, document)))
    if args.samples:
        files.append((Path(args.samples), table.write))
    if args.plot:
        from lensfit.outputs.plots import plot_fit

        files.append((Path(args.plot), lambda tmp: plot_fit(result, tmp, title=f"{source.name}: {result.code}")))
    if args.report:
        from lensfit.outputs.report import write_fit_report

        files.append((Path(args.report), lambda tmp: write_fit_report(
            tmp, result, document, table, stack, title=f"lensfit fit {source}")))
    return write_all(files, force=args.force)


def print_fit(result, document) -> None:
    """Per setting a table of estimates (and truth, when known); diagnostics; reasons."""
    from rich.console import Console
    from rich.table import Table

    from lensfit.outputs.report import budget_text, calibration_text

    show = ("focal_length_mm", "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm",
            "sensor_distance_mm", "aperture_diameter_mm", "blur_floor_px")
    out = Console(width=None if sys.stdout.isatty() else 120)  # logs and pipes get whole rows
    for label, qs in result.settings.items():
        t = Table(title=f"setting {label!r}: {document['settings'][label]['samples']} edges", header_style="bold")
        for col in ("quantity", "estimate ± 1σ", "95% interval"):
            t.add_column(col, justify="right" if col != "quantity" else "left", no_wrap=True)
        rows = {r["quantity"]: r for r in document.get("truth_comparison", []) if r["setting"] == label}
        if rows:
            t.add_column("truth", justify="right", no_wrap=True)
            t.add_column("error", justify="right", no_wrap=True)
        for qn in show:
            e = qs[qn]
            cells = [qn, e.text(), e.interval_text()]
            if rows:
                r = rows.get(qn)
                cells += ([f"{r['truth']:.6g}" if r["truth"] is not None else "infinity",
                           f"{100 * r['relative_error']:+.3f}%" if r["relative_error"] is not None else ""]
                          if r else ["", ""])
            t.add_row(*cells)
        out.print(t)
        if budget := budget_text(qs):
            print(budget)
        eff = qs.get("f_number_effective")
        if eff is not None and eff.value is not None and qs["f_number"].value is not None:
            stops = ((document.get("f_number_definition") or {}).get("stops_down") or {}).get(label)
            where = (f"{stops} stop{'s' if stops != 1 else ''} down" if stops else
                     "wide open" if stops == 0 else "wide open; [lens] widest_f_number narrows it for a lens stopped down")
            print(f"f-number {qs['f_number'].text()} is the nominal one (EFL / entrance pupil); the blur's own reading "
                  f"is {eff.text()} {eff.interval_text()}: real designs' ratio divided out, their spread {where} "
                  "carried in f and N (declare an ideal lens with [lens] ideal = true)")
        cal = (document.get("calibration") or {}).get(label)
        if line := calibration_text(cal):
            print(line)
            dist = cal.get("distortion_opencv") or []
            if any(dist):
                print(f"lens distortion k1 {dist[0]:+.3g}, k2 {dist[1]:+.3g}: each edge's blur is read through it "
                      "(the spot is stretched with the image; flag distortion_scaled in the samples)")
        fc = qs.get("field_curvature_per_m")
        if fc is not None and fc.value is not None:
            print(f"field curvature {fc.value:.3g} ± {fc.sigma:.2g} /m: the in-focus inverse distance at field angle "
                  "a is 1/X + that x tan^2(a); X above is on the axis")
    d = document["diagnostics"]

    def num(x, spec):
        return "n/a" if x is None else format(x, spec)

    pm = document["pupil_magnification"]
    if pm["value"] is not None:
        how = {"fitted": "fitted", "prior": pm.get("reason") or "from the stated range",
               "assumed": "assumed"}[pm["source"]]
        spread = f" ± {pm['sigma']:.3g}" if pm["sigma"] else ""
        lo, hi = pm.get("ci95") or (None, None)
        if pm["sigma"] and lo is not None:
            spread += f", 95 % [{lo:.3g}, {hi:.3g}]" if hi is not None else f", 95 % from {lo:.3g} up"
        print(f"pupil magnification P = {pm['value']:.4g}{spread} ({how}); distances are from the entrance pupil")
    print(f"{d['samples']} samples, {d['outliers']} outlier(s), RMS residual {num(d['rms_residual_px'], '.3f')} px, "
          f"reduced chi-square {num(d['chi2_reduced'], '.2f')}, condition number "
          f"{num(d['condition_number'], '.3g')}, loss {d['loss']}")
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    for r in result.reasons:
        print(f"not identifiable: {r}", file=sys.stderr)


def _fit_outputs(args: argparse.Namespace) -> list[tuple[str, Path]]:
    outputs = [(opt, Path(v)) for opt, v in (("--out", args.out), ("--plot", args.plot), ("--samples", args.samples),
                                              ("--report", args.report)) if v]
    for opt, path in outputs:
        if path.is_dir():
            raise CliError(f"{opt} {path} is a folder; give a file name, e.g. {path / 'results.json'}")
    if args.plot and Path(args.plot).suffix.lower() not in (".png", ".svg", ".pdf"):
        raise CliError(f"--plot must end in .png, .svg or .pdf, got {args.plot!r}")
    if args.samples and Path(args.samples).suffix.lower() not in (".csv", ".json"):
        raise CliError(f"--samples must end in .csv or .json, got {args.samples!r}")
    if args.report and Path(args.report).suffix.lower() not in (".html", ".htm"):
        raise CliError(f"--report must end in .html, got {args.report!r}")
    if args.out and Path(args.out).suffix.lower() != ".json":
        raise CliError(f"--out must end in .json, got {args.out!r}")
    resolved = [p.resolve() for _, p in outputs]
    if len(set(resolved)) < len(resolved):
        raise CliError("--out, --plot, --samples and --report must be different files")
    if Path(args.stack).exists() and Path(args.stack).resolve() in resolved:
        raise CliError(f"an output would replace the input {args.stack}; choose another output name")
    return outputs


def fit_command(args: argparse.Namespace) -> int:
    from lensfit.estimators import ESTIMATORS
    from lensfit.outputs.writers import claimed

    if args.estimator not in ESTIMATORS:
        raise CliError(f"--estimator must be one of {', '.join(ESTIMATORS)}, got {args.estimator!r}")
    forced = isinstance(args.diffraction, float)
    if forced and not (math.isfinite(args.diffraction) and 200.0 <= args.diffraction <= 2000.0):
        raise CliError(f"--diffraction must be an effective wavelength between 200 and 2000 nm (e.g. 550), "
                       f"got {args.diffraction:g}")
    fpx = None
    if args.focal_length_px is not None:
        if not (args.focal_length_px > 0 and math.isfinite(args.focal_length_px)):
            raise InputError("focal_length_px", args.focal_length_px, "> 0 px and finite")
        fpx = args.focal_length_px
    with claimed(_fit_outputs(args), force=args.force):
        return _fit_claimed(args, fpx)


def _fit_claimed(args: argparse.Namespace, fpx: float | None) -> int:
    from rich.console import Console

    source = Path(args.stack)
    console = Console(stderr=True)
    truth = stack = result = None
    rounds: list = []
    forced = isinstance(args.diffraction, float)  # a wavelength; else "auto" or "off"
    options = dict(pixel_pitch_mm=args.pixel_pitch, focal_length_px=fpx, loss=args.loss,
                   blur_floor_px=args.blur_floor, pupil_magnification=args.pupil_magnification,
                   field_curvature=args.field_curvature, spot_shape=args.spot_shape, focusing=args.focusing,
                   ideal_lens=args.ideal_lens, widest_f_number=args.widest_f_number)
    for name in ("focusing", "ideal_lens", "widest_f_number"):
        if options[name] is None:
            del options[name]
    if source.suffix.lower() in (".csv", ".json") and not source.exists():
        raise CliError(f"{source}: no such samples file; give one that 'lensfit measure STACK --out FILE' wrote, "
                       "or a stack folder")
    if source.is_file() and source.suffix.lower() in (".csv", ".json"):
        from lensfit.runtime.jaxcache import enable_compilation_cache
        from lensfit.io.samples import SampleTable

        if forced:
            raise CliError("--diffraction measures the images again; give the stack folder, not a samples file")
        enable_compilation_cache()
        table = SampleTable.read(source)
    else:
        from lensfit.io.stack import load_stack

        stack = load_stack(source, max_pixels=max_pixels_arg(args), allow_outside=args.allow_outside_stack)
        if forced or (args.diffraction == "auto" and args.estimator in ("edge", "edge-disk")):
            table, result, rounds = _measure_with_progress(stack, args, options)
        else:
            table = _measure_with_progress(stack, args)
        truth = _read_truth(stack)
    for w in table.warnings:
        print(f"warning: {w}", file=sys.stderr)

    from lensfit.fitting import fit, results_document
    from lensfit.measurement.processing import apply, from_exif

    if result is None:
        with console.status("fitting"):
            result = fit(table, **options)
        if stack is not None:  # (the pipeline assessed it with the halos; here the EXIF alone)
            apply(result, from_exif(stack), args.processed)
    document = results_document(result, ["lensfit", *args.argv], truth, intrinsics=table.intrinsics,
                                image_shape_px=table.image_shape)
    wavelength = args.diffraction if forced else 550.0
    if rounds:
        document["diffraction"] = {"wavelength_nm": wavelength, "airy_scale_px": rounds[-1], "rounds": len(rounds),
                                   "mode": "forced" if forced else "auto"}
    if table.diffraction is not None:  # the auto test's evidence, whichever way it went
        document["diffraction_test"] = table.diffraction

    written = _write_fit_outputs(args, source, table, result, document, stack)
    if args.json:
        print(json.dumps(document, indent=1))
    else:
        print_fit(result, document)
        if rounds:
            scales = ", ".join(f"{k} {v:.2f} px" for k, v in rounds[-1].items())
            print(f"diffraction modelled at {wavelength:g} nm: Airy scale lambda N_w / p {scales} "
                  f"({len(rounds)} round(s) of measuring)")
        if written:
            print(f"wrote {', '.join(str(p) for p in written)}")
    return EXIT_OK if result.ok else EXIT_NOT_IDENTIFIABLE


def _read_truth(stack) -> dict | None:
    """truth.json of a rendered stack (inside the stack folder only), for the comparison table."""
    truth_path = stack.path / "truth.json"
    if not truth_path.is_file():
        return None
    if not truth_path.resolve().is_relative_to(stack.path.resolve()):
        print(f"warning: {truth_path} points outside the stack folder; not read", file=sys.stderr)
        return None
    from lensfit.errors import SpecError
    from lensfit.io.specs import load_json

    try:
        truth = load_json(truth_path, max_bytes=64 * 1024 * 1024)
    except SpecError as exc:
        print(f"warning: {exc}; no comparison with the truth", file=sys.stderr)
        return None
    if not isinstance(truth, dict):
        print(f"warning: {truth_path} holds no JSON object; no comparison with the truth", file=sys.stderr)
        return None
    return truth
