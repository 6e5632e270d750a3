"""The benchmark commands: ``lensfit bench``, ``bench-fit``, ``bench-lenses``, ``bench-measure``,
``bench-stages``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lensfit.errors import InputError
from lensfit.cli.common import EXIT_BENCH_FAILED, EXIT_OK, CliError, fail_input, progress_bar

def bench_stages_command(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lensfit.bench.stages import run, table

    folder = Path(args.stack)
    if not (folder / "stack.toml").is_file():
        raise CliError(f"STACK {folder}: no stack.toml there; give a stack folder (e.g. out/demo after make demo)")
    import tomllib

    kinds = {t.get("kind") for t in tomllib.loads((folder / "stack.toml").read_text()).get("target", [])}
    if kinds != {"charuco"}:
        raise CliError(f"STACK {folder}: targets {sorted(str(k) for k in kinds)}; bench-stages compares with OpenCV's "
                       "ChArUco detection and needs ChArUco targets only (e.g. out/demo after make demo)")
    if (any(k < 1 for k in args.images) or any(x <= 0 for x in args.scale) or args.repeat < 1 or args.warm_runs < 1
            or any(not 1 <= n <= 5000 for n in args.shots)):
        raise CliError("--images, --scale, --repeat, --warm-runs and --shots must be positive (--shots at most 5000)")
    _check_record_folder(args.record)
    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        report = run(folder, tuple(args.images), tuple(args.scale), repeat=args.repeat, warm_runs=args.warm_runs,
                     jobs=tuple(args.jobs), shots=tuple(args.shots),
                     progress=lambda m, k, n: status.update(f"benchmarking: {m} ({k + 1}/{n})"))
    report["provenance"]["command"] = " ".join(["lensfit", *sys.argv[1:]])
    if args.record:
        from lensfit.bench.records import write_json

        console.print(f"wrote {write_json(args.record, 'stages', report)}")
    print(json.dumps(report, indent=1) if args.json else table(report))
    return EXIT_OK


def _check_record_folder(record: str | None) -> None:
    """``--record DIR``, checked before the work: a folder (or none yet), never a file."""
    if record and Path(record).exists() and not Path(record).is_dir():
        raise CliError(f"--record {record} is a file; give the records' folder (e.g. docs/validation/records)")


def bench_api_command(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lensfit.bench.api import run

    if not (Path(args.stack) / "stack.toml").is_file():
        raise CliError(f"STACK {args.stack}: no stack.toml there; give a stack folder (e.g. out/demo after make demo)")
    if args.pairs < 1:
        raise CliError(f"--pairs must be at least 1, got {args.pairs}")
    _check_record_folder(args.record)
    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        try:
            result = run(args.stack, pairs=args.pairs, progress=lambda m: status.update(f"benchmarking: {m}"))
        except RuntimeError as exc:
            raise CliError(f"STACK {args.stack}: {exc}") from exc
    if args.record:
        from lensfit.bench.records import write_json

        write_json(args.record, "api_vs_cli", result)
    if args.json:
        print(json.dumps(result, indent=1))
        return EXIT_OK
    print(f"lensfit fit {result['median_seconds_cli']:.2f} s, the README's measure_and_fit in a script "
          f"{result['median_seconds_api']:.2f} s (medians of {args.pairs}); ratio {result['median_ratio']:.2f}x")
    return EXIT_OK


def bench_measure_command(args: argparse.Namespace) -> int:
    import json

    from rich.console import Console
    from rich.table import Table

    from lensfit.bench.measure import run, run_exact, run_stack

    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        result = run(draws=args.draws, progress=lambda m: status.update(f"benchmarking: {m}"))
        result["exact"] = run_exact(progress=lambda m: status.update(f"benchmarking: {m}"))
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
    exact = result["exact"]
    table = Table(title=f"edge estimator's relative bias on exact edges (disk x pixel, slants "
                        f"{', '.join(f'{a:g}' for a in exact['slants_deg'])} deg) against the fit's budget")
    for col in ("CoC px", "noise-free min", "noise-free max", f"noise {exact['noise']:g} ({exact['draws']} draws)",
                "budget (1 sigma)"):
        table.add_column(col, justify="right")
    for r in exact["rows"]:
        noisy = "-" if r["noisy_bias"] is None else f"{100 * r['noisy_bias']:+.3f} +- {100 * r['noisy_bias_se']:.3f} %"
        table.add_row(f"{r['coc_diameter_px']:g}", f"{100 * r['bias_min']:+.3f} %", f"{100 * r['bias_max']:+.3f} %",
                      noisy, f"{100 * r['budget']:.3f} %")
    Console().print(table)
    for r in result.get("stack", []):
        print(f"{r['estimator']}: {r['compared']} edges (CoC >= 1.5 px) of {r['edges']}: RMS error "
              f"{r['rms_error_px']:.3f} px, median |error| {r['median_abs_error_px']:.3f} px, bias {r['bias_px']:+.3f} px, "
              f"{100 * r['within_1_sigma']:.0f}% within 1 sigma, {1000 * r['seconds_per_edge']:.0f} ms per edge "
              f"({r['seconds_total']:.1f} s with detection and calibration)")
    return EXIT_OK


def bench_fit_command(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lensfit.bench.noise import run
    from lensfit.runtime.jaxcache import enable_compilation_cache

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


def bench_lenses_command(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lensfit.bench.lenses import record_name, run
    from lensfit.runtime.jaxcache import enable_compilation_cache

    if not 1 <= args.spp <= 65536:
        raise CliError(f"--spp must be between 1 and 65536, got {args.spp}")
    if not 0.1 <= args.scale <= 4:
        raise CliError(f"--scale must be between 0.1 and 4, got {args.scale:g}")
    _check_record_folder(args.record)
    enable_compilation_cache()
    console = Console(stderr=True)
    try:
        with console.status("benchmarking") as status:
            result = run(args.lens or None, spp=args.spp, f_number=None if args.wide_open else args.f_number,
                         progress=lambda m: status.update(f"benchmarking: {m}"),
                         wavelengths_nm=tuple(args.wavelengths or ()), scale=args.scale, keep=args.keep, reuse=args.reuse,
                         designs=args.designs, bracket=args.bracket, focusing=args.focusing, field=args.field)
    except InputError as exc:
        raise fail_input(exc, {"keep": "--keep", "reuse": "--reuse", "field": "--field"}) from exc
    if args.record:
        from lensfit.bench.records import record_header, write_json

        name = record_name(args.bracket, args.focusing, args.designs, None if args.wide_open else args.f_number,
                           args.field, args.scale)
        result.update(record_header(name, " ".join(["lensfit", *sys.argv[1:]])))
        console.print(f"wrote {write_json(args.record, name, result)}")
    if args.json:
        print(json.dumps(result, indent=1))
        return EXIT_OK
    colour = f", grey from {'/'.join(f'{w:g}' for w in args.wavelengths)} nm" if args.wavelengths else ""
    size = f"{round(1200 * args.scale)} x {round(800 * args.scale)} px"
    stops = ("each wide open (far), two stops down (near)" if args.wide_open else
             f"far f/{args.f_number:g}, near f/{result['near_f_number']:g}")
    made = f"stacks from {args.reuse}" if args.reuse else f"{size}, {stops}, {args.spp} spp{colour}"
    table = Table(title=f"real lenses (demo stack scaled to each, {made}): errors of the near setting (and the far "
                        "one in the bracket)")
    for col in ("lens", "P", "fit", "f", "N", "N (real pupil)", "focus distance", "in 95 %", "P fitted"):
        table.add_column(col, justify="right" if col not in ("lens", "fit") else "left")

    def pct(e):
        if e is None:
            return ""
        return "refused" if e["relative_error"] is None else f"{100 * e['relative_error']:+.2f}%"

    def inside(e):
        return f"{sum(bool(e[q]['within_ci95']) for q in ('focal_length_mm', 'f_number', 'focus_distance_mm'))}/3"

    for row in result["rows"]:
        if row.get("refused"):
            table.add_row(row["lens"], "", f"refused: {row['refused']}", "", "", "", "", "", "")
        for how, fr in row["fits"].items():
            e = fr["errors"]
            p_fit = p_fitted_text(how, fr)
            table.add_row(row["lens"], f"{row['pupil_magnification']:.3f}", how, pct(e["focal_length_mm"]),
                          pct(e["f_number"]), pct(e.get("f_number_real_ray")), pct(e["focus_distance_mm"]),
                          inside(e), p_fit)
            if fr.get("errors_far"):
                e = fr["errors_far"]
                table.add_row("", "", "  same fit, far setting", pct(e["focal_length_mm"]), pct(e["f_number"]),
                              pct(e.get("f_number_real_ray")), pct(e["focus_distance_mm"]), inside(e), "")
    Console(width=None if sys.stdout.isatty() else 160).print(table)
    for row in result["rows"]:
        if row.get("refused"):
            continue
        cal = ", ".join(f"{label} {100 * c['relative_error']:+.3f}% (sigma {100 * c['sigma'] / c['focal_length_px']:.3f}%)"
                        for label, c in row["calibration"].items())
        rendered = "reused" if row["seconds_render"] is None else f"render {row['seconds_render']:.0f} s"
        print(f"{row['lens']}: calibrated f_px error {cal}; {rendered}, measure {row['seconds_measure']:.0f} s")
    for how, per in result["coverage"].items():
        cells = []
        for q, c in per.items():
            if c["reported"]:
                lo, hi = c["wilson95"]
                cells.append(f"{q} {c['held']}/{c['reported']} ({100 * lo:.0f}-{100 * hi:.0f} %)"
                             + (f", {c['refused']} refused" if c["refused"] else ""))
        print(f"95 % intervals holding the truth, {how}: " + "; ".join(cells))
    return EXIT_OK


def p_fitted_text(how: str, fit_row: dict) -> str:
    """bench-lenses' "P fitted" cell: the bracket fit's P and sigma, only where that fit gave
    every quantity (beside a refusal P is its starting value, not a finding)."""
    errors = fit_row["errors"]
    refused = fit_row["result"] != "ok" or any(errors.get(q) is None or errors[q]["relative_error"] is None
                                               for q in ("focal_length_mm", "f_number", "focus_distance_mm"))
    if not how.startswith("thick (bracket") or fit_row["pupil_magnification"] is None or refused:
        return ""
    return f"{fit_row['pupil_magnification']:.3f} ± {fit_row['pupil_magnification_sigma']:.3f}"


def bench_command(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lensfit.bench.runs import provenance, run_suite
    from lensfit.bench.suites import list_suites, load_suite
    from lensfit.bench.report import write_report

    if args.jobs < 1:
        raise CliError(f"--jobs must be at least 1, got {args.jobs}")
    try:
        suite = load_suite(args.suite)
    except InputError as exc:
        raise CliError(f"--suite {args.suite!r} is not a suite; available: {', '.join(list_suites())} "
                       "(or the path of a suite .toml)") from exc
    if args.seeds is not None:
        import dataclasses

        suite = dataclasses.replace(suite, seeds=parse_seeds(args.seeds))
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file; give a folder")
    if out.exists() and any(out.iterdir()) and not args.resume:
        raise CliError(f"--out {out} is not empty; pass --resume to continue the run there, or choose another folder")
    _check_record_folder(args.record)
    from lensfit.outputs.writers import OutputLock

    console = Console(stderr=True)
    n_cases = sum(len(t["cases"]) for t in suite.tasks())
    out.parent.mkdir(parents=True, exist_ok=True)
    with OutputLock([("--out", out)]), progress_bar(console, args.progress) as bar:
        task = bar.add_task(f"suite {suite.name}", total=n_cases)
        started = time.perf_counter()
        records = run_suite(suite, out, jobs=args.jobs, resume=args.resume, executor=args.executor,
                            progress=lambda done, total: bar.update(task, completed=done, total=total))
        # what this run took (rendering, measuring, fitting; a resumed run: the cases it ran)
        prov = {**provenance(suite, ["lensfit", *args.argv], args.jobs, args.executor),
                "seconds_wall": round(time.perf_counter() - started, 3)}
        first = out / "cache" / "provenance.json"
        if first.is_file():  # a resumed run: the cases came (partly) from the first run
            prov = {**prov, "first_run": json.loads(first.read_text())}
        else:
            first.write_text(json.dumps(prov, indent=1))
        files = write_report(records, suite, prov, out)
        if args.record:
            from lensfit.bench.records import write_record

            files["record"] = write_record(json.loads(files["json"].read_text()), args.record)
    from lensfit.bench.report import summarise

    summary = summarise(records, suite)
    failed = sum(1 for r in records if r.get("error"))
    missed = sum(1 for r in summary["rows"] if r["passed"] is False)
    print(f"{len(records)} cases ({failed} refused by the input checks) in {prov['seconds_wall'] / 60:.1f} minutes; "
          "wrote " + ", ".join(str(f) for f in files.values()))
    for line in _interval_lines(summary["coverage"]):
        print(line)
    if missed and not args.allow_fail:
        print(f"lensfit bench: {missed} estimate(s) outside the suite's tolerances (FAIL rows in the report); "
              "exit status 4 (--allow-fail: 0)", file=sys.stderr)
        return EXIT_BENCH_FAILED
    return EXIT_OK


def parse_seeds(text: str) -> tuple[int, ...]:
    """``--seeds``: comma-separated seeds and inclusive ranges (``0-9``, ``4,5,6``, ``0-3,10``),
    each a non-negative integer, in the order given with repeats dropped."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, dash, hi = part.strip().partition("-")
        try:
            first, last = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            first = last = -1
        if first < 0 or last < first:
            raise CliError(f"--seeds {text!r}: {part.strip()!r} is not a seed or a range; give non-negative integers "
                           "and ranges low-high, comma-separated (e.g. 0-9 or 0,1,5)")
        seeds += [s for s in range(first, last + 1) if s not in seeds]
    return tuple(seeds)


def _interval_lines(coverage: dict) -> list[str]:
    """The intervals' calibration in a few lines (the report's table): per quantity the 95 %
    coverage with its binomial interval over the effective count, the RMS of error over sigma
    and the mean 95 % half-width over the mean error (a Gaussian with the right sigmas: 1 and
    ``GAUSSIAN_HALF_WIDTH_RATIO``, 2.46x)."""
    from lensfit.bench.coverage import GAUSSIAN_HALF_WIDTH_RATIO

    lines = []
    for q, c in coverage.items():
        if c.get("coverage95") is None:
            continue
        ci = c.get("coverage95_ci95")
        rms, ratio = c.get("rms_error_over_sigma"), c.get("half_width95_over_mean_error")
        lines.append(f"  {q}: {100 * c['coverage95']:.0f} % in the 95 % interval"
                     + (f" ({100 * ci[0]:.0f}-{100 * ci[1]:.0f} %, {c['intervals_effective']:.0f} effective)"
                        if ci else "")
                     + (f", error/sigma RMS {rms:.2f}" if rms is not None else "")
                     + (f", half-width {ratio:.2f}x the error" if ratio is not None else ""))
    if lines:
        lines.insert(0, f"intervals (right sigmas: error/sigma RMS 1, half-width "
                        f"{GAUSSIAN_HALF_WIDTH_RATIO:.2f}x the error):")
    return lines


def bench_hostile_command(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lensfit.bench.hostile import CASES, markdown, run

    unknown = [n for n in args.only or [] if n not in CASES]
    if unknown:
        raise CliError(f"--only {unknown[0]}: not a case; the cases are {', '.join(CASES)}")
    _check_record_folder(args.record)
    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        doc = run(progress=lambda m: status.update(f"benchmarking: {m}"), only=args.only)
    if args.record:
        from lensfit.bench.records import write_json

        write_json(args.record, "hostile", doc)
    print(json.dumps(doc, indent=1) if args.json else markdown(doc))
    return EXIT_OK if doc["passed"] == doc["total"] else EXIT_BENCH_FAILED


def bench_developed_command(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lensfit.bench.developed import markdown, run

    _check_record_folder(args.record)
    if args.keep and Path(args.keep).exists():
        raise CliError(f"--keep {args.keep} exists; give a new folder (nothing of yours is replaced)")
    bad = [n for n in args.f_numbers if not 1.0 <= n <= 32.0]
    if bad:
        raise CliError(f"--f-numbers {bad[0]:g}: give f-numbers from 1 to 32")
    console = Console(stderr=True)
    with console.status("benchmarking") as status:
        doc = run(progress=lambda m: status.update(f"benchmarking: {m}"), developers=tuple(args.developers),
                  keep=Path(args.keep) if args.keep else None, f_numbers=tuple(args.f_numbers))
    if args.record:
        from lensfit.bench.records import write_json

        write_json(args.record, "developed", doc)
    print(json.dumps(doc, indent=1) if args.json else markdown(doc))
    return EXIT_OK if doc["passed"] == doc["total"] else EXIT_BENCH_FAILED
