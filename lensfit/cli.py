"""The ``lensfit`` command line: thin; parses, calls the API, prints.

Heavy modules (JAX, OpenCV) are imported inside the commands, so ``lensfit --help`` answers
at once.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Sequence

from lensfit import __version__
from lensfit.errors import InputError, SpecError

#: Exit codes.
EXIT_OK = 0
EXIT_USAGE = 2  # bad arguments or input files (argparse uses 2 too)
EXIT_NOT_IDENTIFIABLE = 3  # the fit ran, but some parameter cannot be determined from the data
EXIT_BENCH_FAILED = 4  # a benchmark ran, but some case missed its tolerance (lensfit bench)

# Library argument names -> the options a user typed, so that errors name what they wrote.
_MEASURE_OPTIONS = {"estimator": "--estimator", "setting": "setting"}
_FIT_OPTIONS = {**_MEASURE_OPTIONS, "pixel_pitch_mm": "--pixel-pitch", "focal_length_px": "--focal-length-px",
                "loss": "--loss", "blur_floor_px": "--blur-floor", "pupil_magnification": "--pupil-magnification"}

_DOF_OPTIONS = {
    "focal_length_mm": "--focal-length",
    "f_number": "--f-number",
    "focus_distance_mm": "--focus-distance",
    "acceptable_coc_diameter_mm": "--coc",
    "sensor": "--sensor",
    "pixel_pitch_mm": "--pixel-pitch",
}


class CliError(Exception):
    """A one-line message for the user and an exit code."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def _fail_input(exc, options: dict[str, str]) -> CliError:
    """Turn a library InputError into a CLI error naming the option."""
    return CliError(exc.describe(options))


# --------------------------------------------------------------------------- dof


def _fmt_mm(x: float | None) -> str:
    if x is None or math.isinf(x):
        return "infinity"
    if abs(x) >= 1000:
        return f"{x:,.1f} mm ({x / 1000:.3f} m)"
    return f"{x:.3f} mm" if abs(x) < 100 else f"{x:.1f} mm"


def _dof_command(args: argparse.Namespace) -> int:
    from lensfit import optics
    from lensfit.sensors import sensor_format

    try:
        fmt = sensor_format(args.sensor) if args.sensor else None
        pitch = args.pixel_pitch if args.pixel_pitch is not None else (fmt.pixel_pitch_mm if fmt else None)
        if args.pixel_pitch is not None and not (args.pixel_pitch > 0 and math.isfinite(args.pixel_pitch)):
            raise InputError("pixel_pitch_mm", args.pixel_pitch, "> 0 mm and finite")
        if args.coc is not None:
            coc, coc_source = args.coc, "--coc"
        elif fmt is not None:
            coc = float(optics.default_coc_diameter(fmt.width_mm, fmt.height_mm))
            coc_source = f"{fmt.name} diagonal {fmt.diagonal_mm:.2f} mm / 1500"
        else:
            raise CliError("--coc is required unless --sensor names a format (then CoC = diagonal/1500); "
                           "e.g. --coc 0.03 or --sensor full-frame")
        f, N, D = args.focal_length, args.f_number, args.focus_distance
        near = float(optics.near_limit(f, N, coc, D))
        far = float(optics.far_limit(f, N, coc, D))
        dof = float(optics.depth_of_field(f, N, coc, D))
        dof_approx = float(optics.depth_of_field_approx(f, N, coc, D)) if math.isfinite(D) else None
        hyper = float(optics.hyperfocal_distance(f, N, coc))
        s = float(optics.sensor_distance(f, D))
        from_sensor = float(optics.focus_distance_from_sensor(f, D))
        aperture = float(optics.aperture_diameter(f, N))
        mag = float(optics.magnification(f, D))
    except InputError as exc:
        raise _fail_input(exc, _DOF_OPTIONS) from None

    result = {
        "focal_length_mm": f,
        "f_number": N,
        "focus_distance_mm": D if math.isfinite(D) else None,
        "focus_distance_from_sensor_mm": from_sensor if math.isfinite(from_sensor) else None,
        "sensor_distance_mm": s,
        "aperture_diameter_mm": aperture,
        "magnification": mag,
        "acceptable_coc_diameter_mm": coc,
        "acceptable_coc_diameter_px": coc / pitch if pitch else None,
        "coc_source": coc_source,
        "sensor": fmt.name if fmt else None,
        "pixel_pitch_mm": pitch,
        "near_limit_mm": near,
        "far_limit_mm": far if math.isfinite(far) else None,
        "depth_of_field_mm": dof if math.isfinite(dof) else None,
        "depth_of_field_approx_mm": dof_approx,
        "hyperfocal_distance_mm": hyper,
        "beyond_hyperfocal": not math.isfinite(far),
    }
    if fmt is not None:
        result["field_of_view_deg"] = {
            "horizontal": float(optics.field_of_view_deg(fmt.width_mm, f, D)),
            "vertical": float(optics.field_of_view_deg(fmt.height_mm, f, D)),
            "diagonal": float(optics.field_of_view_deg(fmt.diagonal_mm, f, D)),
        }
        result["crop_factor"] = float(optics.crop_factor(fmt.width_mm, fmt.height_mm))
    if args.json:
        print(json.dumps(result, indent=2))
        return EXIT_OK

    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"Depth of field: {f:g} mm f/{N:g} focused at {_fmt_mm(D)} from the lens",
                  show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("near limit", _fmt_mm(near))
    table.add_row("far limit", _fmt_mm(far) + ("  (focus beyond hyperfocal)" if not math.isfinite(far) else ""))
    table.add_row("depth of field (exact)", _fmt_mm(dof))
    if dof_approx is not None:
        table.add_row("depth of field (2NCD²/f²)", _fmt_mm(dof_approx))
    table.add_row("hyperfocal distance", _fmt_mm(hyper))
    coc_px = f" = {coc / pitch:.2f} px at {pitch * 1000:g} µm pitch" if pitch else ""
    table.add_row("acceptable CoC diameter", f"{coc * 1000:.1f} µm{coc_px}")
    table.add_row("  from", coc_source)
    table.add_row("aperture diameter", _fmt_mm(aperture))
    table.add_row("sensor distance (lens to sensor)", _fmt_mm(s))
    table.add_row("focus distance from sensor plane", _fmt_mm(from_sensor))
    table.add_row("magnification at focus", f"{mag:.4g}")
    if fmt is not None:
        fov = result["field_of_view_deg"]
        table.add_row("field of view (h x v, diag)",
                      f"{fov['horizontal']:.1f}° x {fov['vertical']:.1f}°, {fov['diagonal']:.1f}°")
        table.add_row("crop factor", f"{result['crop_factor']:.2f} ({fmt.name})")
    Console().print(table)
    return EXIT_OK


# --------------------------------------------------------------------------- measure


def _max_pixels(args: argparse.Namespace) -> int:
    mp = args.max_megapixels
    if not (math.isfinite(mp) and mp > 0):
        raise CliError(f"--max-megapixels must be a positive number, got {mp:g}")
    return int(mp * 1e6)


def _measure_with_progress(stack, args: argparse.Namespace):
    """``lensfit.measure.measure`` with a progress bar on stderr."""
    from rich.console import Console

    from lensfit.jaxcache import enable_compilation_cache
    from lensfit.measure import measure

    enable_compilation_cache()
    console = Console(stderr=True)
    with _progress_bar(console, args.progress) as bar:
        task = bar.add_task("measuring", total=None)
        return measure(stack, args.estimator,
                       progress=lambda stage, done, total: bar.update(task, description=stage, completed=done,
                                                                      total=total))


def _measure_command(args: argparse.Namespace) -> int:
    from lensfit.estimators import ESTIMATORS
    from lensfit.stack import load_stack

    if args.estimator not in ESTIMATORS:
        raise CliError(f"--estimator must be one of {', '.join(ESTIMATORS)}, got {args.estimator!r}")
    from lensfit.outputs import claimed, write_all

    out = Path(args.out)
    if out.suffix.lower() not in (".csv", ".json"):
        raise CliError(f"--out must end in .csv or .json, got {args.out!r}")
    with claimed([("--out", out)], force=args.force):
        stack = load_stack(args.stack, max_pixels=_max_pixels(args), allow_outside=args.allow_outside_stack)
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


def _bench_measure_command(args: argparse.Namespace) -> int:
    import json

    from rich.console import Console
    from rich.table import Table

    from lensfit.bench_measure import run, run_stack

    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        result = run(draws=args.draws, progress=lambda m: status.update(f"benchmarking: {m}"))
        if args.stack:
            result["stack"] = run_stack(args.stack, progress=lambda m: status.update(f"benchmarking: {m}"))
    if args.json:
        print(json.dumps(result, indent=1))
        return EXIT_OK
    table = Table(title="edge estimator on slanted edges (synth, 256 spp)")
    for col in ("CoC px", "noise", "edges", "RMS error px", "bias px", "median sigma px", "within 1 sigma", "ms/edge"):
        table.add_column(col, justify="right")
    for r in result["rows"]:
        table.add_row(f"{r['coc_diameter_px']:g}", f"{r['noise']:g}", str(r["edges"]), f"{r['rms_error_px']:.3f}",
                      f"{r['bias_px']:+.3f}", f"{r['median_sigma_px']:.3f}", f"{r['within_1_sigma']:.2f}",
                      f"{1000 * r['seconds_per_edge']:.1f}")
    Console().print(table)
    for r in result.get("stack", []):
        print(f"{r['estimator']}: {r['compared']} edges (CoC >= 1.5 px) of {r['edges']}: RMS error "
              f"{r['rms_error_px']:.3f} px, median |error| {r['median_abs_error_px']:.3f} px, bias {r['bias_px']:+.3f} px, "
              f"{100 * r['within_1_sigma']:.0f}% within 1 sigma, {1000 * r['seconds_per_edge']:.0f} ms per edge "
              f"({r['seconds_total']:.1f} s with detection and calibration)")
    return EXIT_OK


# --------------------------------------------------------------------------- fit


def _progress_bar(console, enabled: bool):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), console=console, disable=not console.is_terminal and not enabled)


def _write_fit_outputs(args, source: Path, table, result, document, stack=None) -> list[Path]:
    """Every output to a temporary sibling first, then renamed: all appear, or none."""
    from lensfit.fitting import write_results
    from lensfit.outputs import write_all

    files = []
    if args.out:
        files.append((Path(args.out), lambda tmp: write_results(tmp, document)))
    if args.samples:
        files.append((Path(args.samples), table.write))
    if args.plot:
        from lensfit.plots import plot_fit

        files.append((Path(args.plot), lambda tmp: plot_fit(result, tmp, title=f"{source.name}: {result.code}")))
    if args.report:
        from lensfit.fitreport import write_fit_report

        files.append((Path(args.report), lambda tmp: write_fit_report(
            tmp, result, document, table, stack, title=f"lensfit fit {source}")))
    return write_all(files, force=args.force)


def _print_fit(result, document) -> None:
    """Per setting a table of estimates (and truth, when known); diagnostics; reasons."""
    from rich.console import Console
    from rich.table import Table

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
    d = document["diagnostics"]

    def num(x, spec):
        return "n/a" if x is None else format(x, spec)

    pm = document["pupil_magnification"]
    if pm["value"] is not None:
        how = {"fitted": "fitted", "prior": "from the stated range", "assumed": "assumed"}[pm["source"]]
        spread = f" ± {pm['sigma']:.3g}" if pm["sigma"] else ""
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


def _fit_command(args: argparse.Namespace) -> int:
    from lensfit.estimators import ESTIMATORS
    from lensfit.outputs import claimed

    if args.estimator not in ESTIMATORS:
        raise CliError(f"--estimator must be one of {', '.join(ESTIMATORS)}, got {args.estimator!r}")
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
    truth = stack = None
    if source.suffix.lower() in (".csv", ".json") and not source.exists():
        raise CliError(f"{source}: no such samples file; give one that 'lensfit measure STACK --out FILE' wrote, "
                       "or a stack folder")
    if source.is_file() and source.suffix.lower() in (".csv", ".json"):
        from lensfit.jaxcache import enable_compilation_cache
        from lensfit.measure import SampleTable

        enable_compilation_cache()
        table = SampleTable.read(source)
    else:
        from lensfit.stack import load_stack

        stack = load_stack(source, max_pixels=_max_pixels(args), allow_outside=args.allow_outside_stack)
        table = _measure_with_progress(stack, args)
        truth = _read_truth(stack)
    for w in table.warnings:
        print(f"warning: {w}", file=sys.stderr)

    from lensfit.fitting import fit, results_document

    with console.status("fitting"):
        result = fit(table, pixel_pitch_mm=args.pixel_pitch, focal_length_px=fpx, loss=args.loss,
                     blur_floor_px=args.blur_floor, pupil_magnification=args.pupil_magnification)
    document = results_document(result, ["lensfit", *args.argv], truth, intrinsics=table.intrinsics)

    written = _write_fit_outputs(args, source, table, result, document, stack)
    if args.json:
        print(json.dumps(document, indent=1))
    else:
        _print_fit(result, document)
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
    try:
        return json.loads(truth_path.read_text())
    except (OSError, ValueError) as exc:
        print(f"warning: {truth_path} unreadable ({exc}); no comparison with the truth", file=sys.stderr)
        return None


def _bench_fit_command(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lensfit.bench_fit import run
    from lensfit.jaxcache import enable_compilation_cache

    if not (Path(args.stack) / "truth.json").is_file():
        raise CliError(f"--stack {args.stack} has no truth.json; render one with synth render")
    if args.seeds < 2:
        raise CliError(f"--seeds must be at least 2 (a scatter needs two draws), got {args.seeds}")
    enable_compilation_cache()
    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        result = run(args.stack, seeds=args.seeds, full_well_e=args.full_well, read_noise_e=args.read_noise,
                     estimator=args.estimator, progress=lambda m: status.update(f"benchmarking: {m}"))
    if args.json:
        print(json.dumps(result, indent=1))
        return EXIT_OK
    table = Table(title=f"{args.stack}: {args.seeds} noise draws, full well {args.full_well:g} e-, read noise "
                        f"{args.read_noise:g} e-")
    for col in ("quantity", "clean error", "noisy mean error", "noisy max |error|", "observed scatter",
                "stated sigma", "stated/observed"):
        table.add_column(col, justify="right")
    for r in result["rows"]:
        def pct(x):
            return "refused" if x is None else f"{100 * x:+.3f}%"
        table.add_row(r["quantity"], pct(r["clean_relative_error"]), pct(r["noisy_mean_relative_error"]),
                      f"{100 * r['noisy_max_abs_relative_error']:.3f}%", f"{r['observed_scatter']:.4g}",
                      f"{r['median_stated_sigma']:.4g}",
                      "" if r["stated_over_observed"] is None else f"{r['stated_over_observed']:.2f}")
    Console(width=None if sys.stdout.isatty() else 120).print(table)
    print(f"measure {result['seconds_measure']:.1f} s, fit {result['seconds_fit']:.2f} s per stack")
    return EXIT_OK


def _bench_lenses_command(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lensfit.bench_lenses import run
    from lensfit.jaxcache import enable_compilation_cache

    if not 1 <= args.spp <= 65536:
        raise CliError(f"--spp must be between 1 and 65536, got {args.spp}")
    enable_compilation_cache()
    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        result = run(args.lens or None, spp=args.spp, f_number=args.f_number,
                     progress=lambda m: status.update(f"benchmarking: {m}"),
                     wavelengths_nm=tuple(args.wavelengths or ()))
    if args.json:
        print(json.dumps(result, indent=1))
        return EXIT_OK
    colour = f", grey from {'/'.join(f'{w:g}' for w in args.wavelengths)} nm" if args.wavelengths else ""
    table = Table(title=f"real lenses (demo stack scaled to each, f/{args.f_number:g}, {args.spp} spp{colour}): errors "
                        "of the near setting (and the far one in the bracket)")
    for col in ("lens", "P", "fit", "f", "N", "N (real pupil)", "focus distance", "in 95 %", "P fitted"):
        table.add_column(col, justify="right" if col not in ("lens", "fit") else "left")

    def pct(e):
        if e is None:
            return ""
        return "refused" if e["relative_error"] is None else f"{100 * e['relative_error']:+.2f}%"

    def inside(e):
        return f"{sum(bool(e[q]['within_ci95']) for q in ('focal_length_mm', 'f_number', 'focus_distance_mm'))}/3"

    for row in result["rows"]:
        for how, fr in row["fits"].items():
            e = fr["errors"]
            p_fit = "" if not how.startswith("thick (bracket") or fr["pupil_magnification"] is None else \
                f"{fr['pupil_magnification']:.3f} ± {fr['pupil_magnification_sigma']:.3f}"
            table.add_row(row["lens"], f"{row['pupil_magnification']:.3f}", how, pct(e["focal_length_mm"]),
                          pct(e["f_number"]), pct(e.get("f_number_real_ray")), pct(e["focus_distance_mm"]),
                          inside(e), p_fit)
            if fr.get("errors_far"):
                e = fr["errors_far"]
                table.add_row("", "", "  same fit, far setting", pct(e["focal_length_mm"]), pct(e["f_number"]),
                              pct(e.get("f_number_real_ray")), pct(e["focus_distance_mm"]), inside(e), "")
    Console(width=None if sys.stdout.isatty() else 160).print(table)
    for row in result["rows"]:
        cal = ", ".join(f"{label} {100 * c['relative_error']:+.3f}% (sigma {100 * c['sigma'] / c['focal_length_px']:.3f}%)"
                        for label, c in row["calibration"].items())
        print(f"{row['lens']}: calibrated f_px error {cal}; render {row['seconds_render']:.0f} s, "
              f"measure {row['seconds_measure']:.0f} s")
    return EXIT_OK


def _bench_command(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lensfit.bench import list_suites, load_suite, provenance, run_suite
    from lensfit.report import write_report

    if args.jobs < 1:
        raise CliError(f"--jobs must be at least 1, got {args.jobs}")
    try:
        suite = load_suite(args.suite)
    except InputError as exc:
        raise CliError(f"--suite {args.suite!r} is not a suite; available: {', '.join(list_suites())} "
                       "(or the path of a suite .toml)") from exc
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file; give a folder")
    if out.exists() and any(out.iterdir()) and not args.resume:
        raise CliError(f"--out {out} is not empty; pass --resume to continue the run there, or choose another folder")
    from lensfit.outputs import OutputLock

    console = Console(stderr=True)
    n_cases = sum(len(t["cases"]) for t in suite.tasks())
    out.parent.mkdir(parents=True, exist_ok=True)
    with OutputLock([("--out", out)]), _progress_bar(console, args.progress) as bar:
        task = bar.add_task(f"suite {suite.name}", total=n_cases)
        records = run_suite(suite, out, jobs=args.jobs, resume=args.resume, executor=args.executor,
                            progress=lambda done, total: bar.update(task, completed=done, total=total))
        prov = provenance(suite, ["lensfit", *args.argv], args.jobs, args.executor)
        first = out / "cache" / "provenance.json"
        if first.is_file():  # a resumed run: the cases came (partly) from the first run
            prov = {**prov, "first_run": json.loads(first.read_text())}
        else:
            first.write_text(json.dumps(prov, indent=1))
        files = write_report(records, suite, prov, out)
    from lensfit.report import summarise

    failed = sum(1 for r in records if r.get("error"))
    missed = sum(1 for r in summarise(records, suite)["rows"] if r["passed"] is False)
    print(f"{len(records)} cases ({failed} refused by the input checks); wrote "
          + ", ".join(str(f) for f in files.values()))
    if missed and not args.allow_fail:
        print(f"lensfit bench: {missed} estimate(s) outside the suite's tolerances (FAIL rows in the report); "
              "exit status 4 (--allow-fail: 0)", file=sys.stderr)
        return EXIT_BENCH_FAILED
    return EXIT_OK


# --------------------------------------------------------------------------- target

_TARGET_OPTIONS = {"paper": "--paper", "squares": "--squares", "square_mm": "--square-mm",
                   "marker_mm": "--marker-mm", "dictionary": "--dictionary", "dpi": "--dpi"}


def _target_command(args: argparse.Namespace) -> int:
    from lensfit.outputs import claimed, write_all
    from lensfit.printable import charuco_page, target_toml, write_page

    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".pdf"):
        raise CliError(f"--out {out}: give a .pdf or .png file name")
    try:
        board = charuco_page(args.paper, tuple(args.squares), args.square_mm, args.marker_mm, args.dictionary,
                             args.dpi, args.id)
    except InputError as exc:
        raise _fail_input(exc, _TARGET_OPTIONS) from None
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
          f"{board.page_mm[0]:g} x {board.page_mm[1]:g} mm, {board.dpi:.1f} dpi.")
    print("# Print at 100 % (actual size), mount it flat, measure a square: where it is not "
          f"{e['square_mm']:g} mm, scale square_mm and marker_mm below by the measured ratio.")
    print("# stack.toml entry:")
    print(target_toml(e), end="")
    return EXIT_OK


# --------------------------------------------------------------------------- init

_INIT_OPTIONS = {"pixel_pitch_mm": "--pixel-pitch", "sensor_width_mm": "--sensor-width", "sensor": "--sensor",
                 "settings": "--settings", "prefer": "--prefer", "photos": "PHOTOS_DIR"}


def _init_command(args: argparse.Namespace) -> int:
    from lensfit.manifest import draft_manifest
    from lensfit.outputs import claimed, write_text

    folder = Path(args.photos)
    out = Path(args.out) if args.out else folder / "stack.toml"
    if out.suffix.lower() != ".toml":
        raise CliError(f"--out {out}: give a .toml file name (lensfit reads stack.toml)")
    if folder.is_dir() and out.parent.resolve() != folder.resolve():
        raise CliError(f"--out {out}: write it into {folder} (a manifest names its images relative to itself), "
                       f"e.g. --out {folder / 'stack-jpeg.toml'}")
    try:
        with claimed([("--out", out)], force=args.force):
            draft = draft_manifest(folder, target_file=args.target, pixel_pitch_mm=args.pixel_pitch,
                                   sensor=args.sensor, sensor_width_mm=args.sensor_width, grouping=args.settings,
                                   prefer=args.prefer, max_pixels=int(args.max_megapixels * 1e6))
            write_text(out, draft.text, force=args.force)
    except InputError as exc:
        raise _fail_input(exc, _INIT_OPTIONS) from None
    print(f"wrote {out}: {len(draft.rows)} image(s), {len({r['setting'] for r in draft.rows})} setting(s)")
    print(f"{'file':<28} {'setting':>7} {'f (mm)':>8} {'N':>6} {'focus (mm)':>11}")
    for r in draft.rows:
        def show(x, spec):
            return "-" if x is None else ("inf" if math.isinf(x) else format(x, spec))
        print(f"{r['file'][:28]:<28} {r['setting']:>7} {show(r['focal_length_mm'], '8.4g'):>8} "
              f"{show(r['f_number'], '6.3g'):>6} {show(r['focus_distance_mm'], '11.5g'):>11}")
    for note in draft.notes:
        print(f"note: {note}")
    dest = out.parent if out.name == "stack.toml" else out
    print(f"next: check the setting labels and the target in {out}, then: lensfit fit {dest}")
    return EXIT_OK


# --------------------------------------------------------------------------- plan

_PLAN_OPTIONS = {"focal_length_mm": "--focal-length", "f_number": "--f-number", "focus_distance_mm": "--focus-distance",
                 "pixel_pitch_mm": "--pixel-pitch", "goal": "--goal", "max_shots": "--max-shots",
                 "width_px": "--width-px", "target": "--target", "target.kind": "--target's kind"}


def _plan_command(args: argparse.Namespace) -> int:
    from lensfit.plan import QUANTITIES, Board, blur_at, plan_capture
    from lensfit.sensors import sensor_format

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
        if args.target:
            from lensfit.specs import load_toml

            entries = load_toml(args.target).get("target") or []
            if not entries:
                raise CliError(f"--target {args.target}: no [[target]] table; give the file lensfit target --entry wrote")
            entry = entries[0]
        else:
            from lensfit.printable import charuco_page

            entry = charuco_page().entry
        board = Board.from_entry(entry)
        plan = plan_capture(args.focal_length, args.f_number, args.focus_distance, pixel_pitch_mm=pitch,
                            width_px=int(width_px), height_px=int(height_px), board=board, goal_rel=args.goal / 100,
                            max_shots=args.max_shots, edge_sigma_px=args.edge_sigma_px,
                            edge_sigma_rel=args.edge_sigma_rel / 100,
                            calibration_sigma_rel=args.calibration_sigma / 100)
    except InputError as exc:
        raise _fail_input(exc, _PLAN_OPTIONS) from None
    if args.json:
        print(json.dumps(plan.to_json_dict(), indent=1))
        return EXIT_OK
    print(f"lens guess f {args.focal_length:g} mm, f/{args.f_number:g}, focus {_fmt_mm(args.focus_distance)}; "
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
            print(f"  {row['shots']:>3} shots: " + ", ".join(
                f"{100 * 1.96 * row[q]:.2g} %" if math.isfinite(row[q]) else "-" for q in QUANTITIES))
    for note in plan.notes:
        print(f"note: {note}")
    print("note: a lower bound for an unbiased fit; tilt some shots by 20-40 degrees for the calibration")
    return EXIT_OK


# --------------------------------------------------------------------------- parser


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def _pupil(text: str) -> float | tuple[float, float]:
    """``--pupil-magnification``: a number, or ``LO:HI``."""
    try:
        if ":" in text:
            lo, hi = text.split(":", 1)
            return float(lo), float(hi)
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or LO:HI, got {text!r}") from None


def _input_options(p: argparse.ArgumentParser, outside: bool = True) -> None:
    """Options on reading a stack: the pixel budget and reading outside the stack folder."""
    from lensfit.limits import DEFAULT_MAX_MEGAPIXELS

    p.add_argument("--max-megapixels", type=_number, default=DEFAULT_MAX_MEGAPIXELS, metavar="MP",
                   help=f"refuse images larger than this, checked from the file header before decoding "
                        f"(default {DEFAULT_MAX_MEGAPIXELS:g})")
    if outside:
        p.add_argument("--allow-outside-stack", action="store_true",
                       help="read image files that stack.toml names outside the stack folder (refused by default)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lensfit",
        description="Measure defocus blur in image stacks and recover focal length, f-number and "
                    "focus distance. All lengths in millimetres.")
    parser.add_argument("--version", action="version", version=f"lensfit {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    dof = sub.add_parser(
        "dof", help="depth-of-field calculator (thin lens)",
        description="Depth of field of a thin lens: near and far limits, total DOF, hyperfocal "
                    "distance. Distances are from the lens plane, in mm.")
    dof.add_argument("--focal-length", type=_number, required=True, metavar="MM",
                     help="focal length f, mm (> 0)")
    dof.add_argument("--f-number", type=_number, required=True, metavar="N",
                     help="f-number N (> 0)")
    dof.add_argument("--focus-distance", type=_number, required=True, metavar="MM",
                     help="focus distance D_s from the lens plane, mm (> focal length; 'inf' allowed)")
    dof.add_argument("--coc", type=_number, metavar="MM",
                     help="acceptable circle-of-confusion diameter, mm (default: sensor diagonal / 1500)")
    dof.add_argument("--sensor", metavar="NAME",
                     help="sensor format, e.g. full-frame, aps-c, micro-four-thirds (data_specs/sensor_formats.toml)")
    dof.add_argument("--pixel-pitch", type=_number, metavar="MM",
                     help="pixel pitch, mm, to express the CoC in pixels (default: from --sensor when known)")
    dof.add_argument("--json", action="store_true", help="print a JSON object instead of a table")
    dof.set_defaults(func=_dof_command, prog="lensfit dof")

    tg = sub.add_parser("target", help="write a printable ChArUco board (PDF/PNG) and its stack.toml entry",
                        description="Lay out a ChArUco board at its true size on a sheet of paper (PDF or PNG, "
                                    "by --out's suffix) and print the [[target]] entry of stack.toml that "
                                    "describes it. Print at 100 % and measure a square before use.")
    tg.add_argument("--out", required=True, metavar="FILE", help="board.pdf or board.png")
    tg.add_argument("--paper", default="a4-landscape", metavar="SIZE",
                    help="a4, a3, a2, letter, tabloid (+ -landscape) or WxH in mm (default a4-landscape)")
    tg.add_argument("--squares", type=int, nargs=2, default=(9, 6), metavar=("COLS", "ROWS"),
                    help="squares across and down (default 9 6)")
    tg.add_argument("--square-mm", type=_number, metavar="MM", help="square side (default: the largest that fits)")
    tg.add_argument("--marker-mm", type=_number, metavar="MM", help="marker side (default 0.75 x the square)")
    tg.add_argument("--dictionary", default="DICT_5X5_100", metavar="NAME",
                    help="OpenCV ArUco dictionary (default DICT_5X5_100)")
    tg.add_argument("--dpi", type=_number, default=300.0, help="at least this resolution (default 300)")
    tg.add_argument("--id", default="board", help="the target's id in stack.toml (default board)")
    tg.add_argument("--entry", metavar="FILE.toml",
                    help="also write the [[target]] entry to this file (for lensfit init --target)")
    tg.add_argument("--force", action="store_true", help="replace an existing board this program wrote")
    tg.set_defaults(func=_target_command, prog="lensfit target")

    it = sub.add_parser("init", help="write stack.toml for a folder of photos from their EXIF",
                        description="Draft PHOTOS_DIR/stack.toml from the photos' EXIF: the images (RAW preferred "
                                    "over the JPEG of a RAW + JPEG pair), setting labels grouped by f-number and "
                                    "focus distance, the pixel pitch (EXIF FocalPlaneXResolution, or the camera in "
                                    "data_specs/cameras.toml) and the target (--target). Reads the photos' headers "
                                    "only; check the draft before fitting.")
    it.add_argument("photos", metavar="PHOTOS_DIR", help="folder holding the photos of the target")
    it.add_argument("--target", metavar="FILE.toml",
                    help="[[target]] entry of the printed board (lensfit target --entry FILE; or a stack.toml); "
                         "default: the board lensfit target draws by default, noted as assumed")
    it.add_argument("--pixel-pitch", type=_number, metavar="MM", help="sensor pixel pitch, mm (overrides the EXIF)")
    it.add_argument("--sensor-width", type=_number, metavar="MM",
                    help="sensor active width, mm (the pitch is this / image width)")
    it.add_argument("--sensor", metavar="NAME", help="a sensor format of data_specs/sensor_formats.toml")
    it.add_argument("--settings", default="exif", choices=["exif", "per-image", "one"],
                    help="setting labels: by the EXIF f-number and focus distance (default), one per image, or one")
    it.add_argument("--prefer", default="raw", choices=["raw", "jpeg"],
                    help="which file of a RAW + JPEG pair to list (default raw: linear, no tone curve)")
    it.add_argument("--out", metavar="FILE", help="manifest to write (default PHOTOS_DIR/stack.toml)")
    it.add_argument("--force", action="store_true", help="replace a stack.toml lensfit init wrote")
    _input_options(it, outside=False)
    it.set_defaults(func=_init_command, prog="lensfit init")

    pl = sub.add_parser("plan", help="where to put the target and how many shots for a requested accuracy",
                        description="Plan a capture for a lens guess: the usable target distances (the board fits, "
                                    "its squares are detectable, the blur leaves them readable), shots spread evenly in "
                                    "inverse distance over them, and the Cramer-Rao bound of f, N and the focus "
                                    "distance against the number of shots; the smallest number reaching --goal.")
    pl.add_argument("--focal-length", type=_number, required=True, metavar="MM", help="focal length guess, mm")
    pl.add_argument("--f-number", type=_number, required=True, metavar="N", help="f-number of the capture")
    pl.add_argument("--focus-distance", type=_number, required=True, metavar="MM",
                    help="focus distance from the lens, mm ('inf' allowed)")
    pl.add_argument("--sensor", metavar="NAME", help="sensor format with a pixel grid (data_specs/sensor_formats.toml)")
    pl.add_argument("--pixel-pitch", type=_number, metavar="MM", help="pixel pitch, mm")
    pl.add_argument("--width-px", type=int, metavar="PX", help="image width, px")
    pl.add_argument("--height-px", type=int, metavar="PX", help="image height, px")
    pl.add_argument("--target", metavar="FILE.toml",
                    help="the board's [[target]] entry (lensfit target --entry); default: lensfit target's default board")
    pl.add_argument("--goal", type=_number, default=1.0, metavar="PCT",
                    help="95%% half-interval to reach on f, N and focus distance, per cent (default 1)")
    pl.add_argument("--max-shots", type=int, default=48, metavar="N", help="largest capture considered (default 48)")
    pl.add_argument("--edge-sigma-px", type=_number, default=0.05, metavar="PX",
                    help="blur measurement noise per edge, px (default 0.05)")
    pl.add_argument("--edge-sigma-rel", type=_number, default=2.0, metavar="PCT",
                    help="and its part proportional to the blur, per cent (default 2)")
    pl.add_argument("--calibration-sigma", type=_number, default=0.1, metavar="PCT",
                    help="1-sigma of the calibrated focal length in px, per cent (default 0.1)")
    pl.add_argument("--json", action="store_true", help="print the plan as JSON")
    pl.set_defaults(func=_plan_command, prog="lensfit plan")

    m = sub.add_parser(
        "measure", help="measure blur diameter versus distance on the targets of an image stack",
        description="Detect the targets of STACK (a folder with stack.toml), calibrate, solve poses and "
                    "measure the blur-disk diameter on every target edge.")
    m.add_argument("stack", help="stack folder (or its stack.toml)")
    m.add_argument("--out", required=True, metavar="FILE", help="samples file: .csv or .json")
    m.add_argument("--estimator", default="edge", metavar="NAME",
                   help="blur estimator: edge (fast; second-moment blur diameter), edge-disk (uniform-disk reading) "
                        "or target (analysis by synthesis)")
    m.add_argument("--force", action="store_true", help="replace an existing --out file that lensfit wrote")
    _input_options(m)
    m.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    m.set_defaults(func=_measure_command, prog="lensfit measure")

    ft = sub.add_parser(
        "fit", help="measure a stack and fit focal length, f-number and focus distance",
        description="Measure blur on every target edge of STACK (a folder with stack.toml; or a samples "
                    ".json/.csv from 'lensfit measure') and fit the circle-of-confusion model: the shared "
                    "focal length and, per setting, f-number and focus distance, with 1-sigma and 95% "
                    "intervals. Exit status 0: every parameter determined; 3: the fit ran but some parameter "
                    "is not identifiable (the results say which and why); 2: bad input.")
    ft.add_argument("stack", help="stack folder (or its stack.toml), or a samples .json/.csv")
    ft.add_argument("--estimator", default="edge", metavar="NAME",
                    help="blur estimator: edge (fast; second-moment blur diameter), edge-disk (uniform-disk reading) "
                        "or target (analysis by synthesis)")
    ft.add_argument("--out", metavar="FILE", help="results JSON (data_specs/schemas/results.schema.json)")
    ft.add_argument("--plot", metavar="FILE", help="plot of blur versus inverse distance and the fit (.png/.svg/.pdf)")
    ft.add_argument("--samples", metavar="FILE", help="also write the measured samples (.csv/.json)")
    ft.add_argument("--report", metavar="FILE.html",
                    help="one self-contained HTML page: estimates, the fit plot and per image the detected corners "
                         "and measured edges coloured by blur and by residual")
    ft.add_argument("--loss", default="huber", choices=["huber", "cauchy", "linear"],
                    help="robust loss (default huber; cauchy for many outliers)")
    ft.add_argument("--blur-floor", type=_number, metavar="PX",
                    help="fix the blur floor (px) instead of fitting it per setting")
    ft.add_argument("--pupil-magnification", type=_pupil, metavar="P|LO:HI",
                    help="pupil magnification P (exit / entrance pupil diameter) of a thick lens: a value to assume, "
                         "or a range LO:HI (a prior whose 95%% interval it is; widens f and N honestly). Default: "
                         "fitted from two or more focus settings, else 1 (thin lens) with a warning")
    ft.add_argument("--pixel-pitch", type=_number, metavar="MM",
                    help="pixel pitch, mm (for samples without it, e.g. a CSV of your own)")
    ft.add_argument("--focal-length-px", type=_number, metavar="PX",
                    help="calibrated focal length in px (overrides the samples file's; for samples without one)")
    ft.add_argument("--json", action="store_true", help="print the results JSON instead of tables")
    ft.add_argument("--force", action="store_true", help="replace existing output files that lensfit wrote")
    _input_options(ft)
    ft.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    ft.set_defaults(func=_fit_command, prog="lensfit fit")

    bs = sub.add_parser("bench", help="run a benchmark suite and write its report",
                        description="Run a suite of data_specs/bench/ (scenes x render quality x noise x "
                                    "estimators x solver settings x seeds): render, measure and fit each case, then "
                                    "write results.json, report.md and a self-contained report.html to --out. "
                                    "Finished cases are cached: --resume continues an interrupted run.")
    bs.add_argument("--suite", default="quick", metavar="NAME", help="quick (default), standard, hard, or a .toml path")
    bs.add_argument("--out", required=True, metavar="DIR", help="output folder (new or empty, unless --resume)")
    bs.add_argument("--jobs", type=int, default=1, metavar="N", help="parallel processes or Dask workers (default 1)")
    bs.add_argument("--resume", action="store_true", help="continue a run in --out, keeping finished cases")
    bs.add_argument("--executor", default="local", metavar="KIND",
                    help="local (process pool, default), dask (a local Dask cluster) or dask://HOST:PORT")
    bs.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    bs.add_argument("--allow-fail", action="store_true",
                    help="exit 0 even when estimates miss the suite's tolerances (default: exit status 4)")
    bs.set_defaults(func=_bench_command, prog="lensfit bench")

    bf = sub.add_parser("bench-fit", help="accuracy of f, N, focus distance and honesty of sigma under noise",
                        description="Measure and fit a rendered STACK (with truth.json) clean and with seeded "
                                    "photon + read noise; report errors, observed scatter and stated sigma.")
    bf.add_argument("--stack", required=True, metavar="DIR", help="a stack rendered by synth (linear PNGs)")
    bf.add_argument("--seeds", type=int, default=5, help="noise draws (default 5)")
    bf.add_argument("--full-well", type=_number, default=20000.0, metavar="E", help="electrons at white (20000)")
    bf.add_argument("--read-noise", type=_number, default=5.0, metavar="E", help="read noise, electrons (5)")
    bf.add_argument("--estimator", default="edge", metavar="NAME", help="blur estimator (edge)")
    bf.add_argument("--json", action="store_true", help="print JSON")
    bf.set_defaults(func=_bench_fit_command, prog="lensfit bench-fit")

    bl = sub.add_parser("bench-lenses", help="thin- and thick-lens fits on stacks ray traced through real lenses",
                        description="Render the demo calibration stack through every shipped compound lens "
                                    "(data_specs/lenses) at two focus distances, and fit it as a thin lens (one setting), "
                                    "as a thick lens with P given, and as a thick lens with P fitted from the bracket.")
    bl.add_argument("--lens", action="append", metavar="NAME", help="only this design (repeatable)")
    bl.add_argument("--spp", type=int, default=64, help="ray-tracing samples per pixel (default 64)")
    bl.add_argument("--f-number", type=_number, default=11.0, metavar="N",
                    help="f-number of every shot (default 11; faster than a design opens to is refused)")
    bl.add_argument("--wavelengths", type=_number, nargs="+", metavar="NM",
                    help="render grey through these wavelengths (glass dispersion: longitudinal and lateral colour); "
                         "only the designs whose glasses are known (default: the d line alone)")
    bl.add_argument("--json", action="store_true", help="print JSON")
    bl.set_defaults(func=_bench_lenses_command, prog="lensfit bench-lenses")

    bm = sub.add_parser("bench-measure", help="accuracy and time per edge of the blur estimators",
                        description="Benchmark: slanted edges rendered by synth at several CoC diameters and "
                                    "noise levels; optionally both estimators on a rendered STACK with truth.")
    bm.add_argument("--stack", metavar="DIR", help="also run every estimator on this rendered stack")
    bm.add_argument("--draws", type=int, default=3, help="noise draws per case (default 3)")
    bm.add_argument("--json", action="store_true", help="print JSON")
    bm.set_defaults(func=_bench_measure_command, prog="lensfit bench-measure")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from lensfit.outputs import run_guarded

    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv

    def known(exc: Exception):
        if isinstance(exc, CliError):
            return str(exc), exc.code
        if isinstance(exc, InputError):  # input errors the command did not map itself
            return exc.describe(_FIT_OPTIONS), EXIT_USAGE
        return None

    return run_guarded(args.prog, lambda: args.func(args), known)


if __name__ == "__main__":
    sys.exit(main())
