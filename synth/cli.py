"""The ``synth`` command line: thin; parses, calls the API, prints.

``synth --help`` answers without importing JAX.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

from lensfit import __version__
from lensfit.errors import InputError

EXIT_OK = 0
EXIT_USAGE = 2

_OPTIONS = {"method": "--method", "samples_per_pixel": "--spp", "seed": "--seed", "out": "--out",
            "image_format": "--format", "supersampling": "--supersampling", "preview": "--preview",
            "mitsuba_variant": "--mitsuba-variant", "pairs": "--pairs"}


def _render_command(args: argparse.Namespace) -> int:
    from synth.scene import load_scene
    from synth.stack import check_out_dir

    from lensfit.outputs.writers import OutputLock, check_output

    scene = load_scene(args.scene)
    check_out_dir(args.out, args.force)  # refuse before spending time on the render
    outputs = [("--out", Path(args.out))]
    if args.preview is not None:
        preview = Path(args.preview)
        if preview.suffix.lower() != ".png":
            raise InputError("preview", args.preview, "a .png file name")
        if preview.resolve().is_relative_to(Path(args.out).resolve()):
            raise InputError("preview", args.preview, "a file outside --out", "the stack folder holds only the stack")
        preview.parent.mkdir(parents=True, exist_ok=True)
        check_output(preview, "--preview", force=args.force)
        outputs.append(("--preview", preview))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with OutputLock(outputs):
        return _render_locked(args, scene)


def _render_locked(args: argparse.Namespace, scene) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from lensfit.runtime.jaxcache import enable_compilation_cache
    from lensfit.outputs.writers import check_output
    from synth.rendering import check_overrides, render
    from synth.stack import check_out_dir, write_stack

    check_out_dir(args.out, args.force)  # again, under the lock
    if args.preview is not None:
        check_output(args.preview, "--preview", force=args.force)
    console = Console(stderr=True)
    enable_compilation_cache()
    check_overrides(samples_per_pixel=args.spp, seed=args.seed, supersampling=args.supersampling)
    scene = scene.with_render(method=args.method, samples_per_pixel=args.spp, seed=args.seed,
                              supersampling=args.supersampling, mitsuba_variant=args.mitsuba_variant)
    total_rows = sum(s.camera.height_px for s in scene.shots)
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console,
                  disable=not console.is_terminal and not args.progress) as bar:
        task = bar.add_task(f"rendering {len(scene.shots)} shot(s)", total=total_rows)
        finished = {}

        def progress(name, done, height):
            finished[name] = done
            bar.update(task, completed=sum(finished.values()), description=f"rendering {name}")

        result = render(scene, image_format=args.format, progress=progress)
    out = write_stack(result, args.out, force=args.force)
    methods = ", ".join(sorted({i["method"] for i in result.truth["images"]}))
    print(f"wrote {len(result.images)} image(s), stack.toml and truth.json to {out} (method: {methods})")
    totals: dict[str, float] = {}
    for seconds in result.stage_seconds.values():
        for stage, t in seconds.items():
            totals[stage] = totals.get(stage, 0.0) + t
    print("seconds per stage (all shots, compilation included): "
          + ", ".join(f"{stage} {t:.2f}" for stage, t in totals.items()))
    if args.preview is not None:
        from synth.preview import recorded, write_preview

        write_preview(args.preview, recorded(result), force=args.force)
        print(f"wrote the contact sheet {args.preview}")
    return EXIT_OK


def _plan_command(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from synth.rendering import check_overrides, plan
    from synth.scene import load_scene

    check_overrides(samples_per_pixel=args.spp)
    scene = load_scene(args.scene).with_render(method=args.method, samples_per_pixel=args.spp)
    plans = plan(scene)
    r = scene.render
    table = Table(title=f"{scene.name}: {len(plans)} shot(s), {scene.width_px} x {scene.height_px} px, "
                        f"effects: {', '.join(r.effects)}")
    for col in ("shot", "setting", "method", "work", "est. time"):
        table.add_column(col)
    reasons: dict[str, list[str]] = {}
    pipelines: dict[tuple, list] = {}
    for p in plans:
        table.add_row(p.shot.name, p.shot.setting, p.method + ("" if p.exact else " (NOT exact)"), p.work,
                      f"{p.estimated_s:.2f} s")
        reasons.setdefault(p.reason, []).append(p.shot.name)
        pipelines.setdefault(p.stages, []).append(p)
    console = Console()
    console.print(table)
    for reason, names in reasons.items():
        print(f"{', '.join(names)}: {reason}")
    for stages, group in pipelines.items():
        st = Table(title=f"stages of {', '.join(p.shot.name for p in group[:4])}{' ...' if len(group) > 4 else ''}")
        st.add_column("#", justify="right")
        st.add_column("stage")
        st.add_column("est. time", justify="right")
        for i, (name, secs) in enumerate(zip(stages, group[0].stage_seconds), 1):
            st.add_row(str(i), name, f"{secs:.2f} s")
        console.print(st)
    print(f"estimated total: {sum(p.estimated_s for p in plans):.1f} s (after compilation)")
    return EXIT_OK


def _bench_command(args: argparse.Namespace) -> int:
    import json

    from rich.console import Console
    from rich.table import Table

    from lensfit.runtime.jaxcache import enable_compilation_cache
    from synth.bench import run_bench

    console = Console(stderr=True)
    if args.plan_costs:
        from synth import plan_costs

        with console.status("benchmarking") as status:
            result = plan_costs.run(progress=lambda msg: status.update(f"benchmarking: {msg}"))
        if args.record:
            console.print(f"wrote {plan_costs.record(result, args.record)}")
        if args.json:
            print(json.dumps(result, indent=1))
            return EXIT_OK
        table = Table(title=f"synth plan's estimates against warm renders, {result['cores']} cores")
        for col in ("scene", "shots", "estimated s", "measured s", "measured / estimated"):
            table.add_column(col, justify="right")
        for r in result["cases"]:
            table.add_row(r["case"], str(r["shots"]), f"{r['estimated_s']:.2f}", f"{r['measured_s']:.2f}",
                          f"{r['ratio']:.2f}" + ("" if r["within"] else " (outside)"))
        Console().print(table)
        print(f"{result['passed']} of {result['total']} within {result['within_factor']:g}x")
        return EXIT_OK
    if args.against_mitsuba:
        from synth.bench import against_mitsuba, mitsuba_record, record
        from synth.rendering import check_overrides

        for spp in args.spp:
            check_overrides(samples_per_pixel=spp)
        if args.pairs < 1:
            raise InputError("pairs", args.pairs, ">= 1")
        if args.record and args.scene:
            raise InputError("--scene", args.scene, "given only without --record",
                             "a record is always the demo scene's")

        with console.status("benchmarking") as status:
            def progress(msg):
                status.update(f"benchmarking: {msg}")
            results = [against_mitsuba(args.scene, spp, args.pairs, args.mitsuba_variant, progress=progress)
                       for spp in args.spp]
            doc = mitsuba_record(results, args.pairs, progress, args.record) if args.record else None
        if doc is not None:
            console.print(f"wrote {record(doc, args.record)}")
        if args.json:
            print(json.dumps(doc if doc is not None else results[0] if len(results) == 1 else results, indent=1))
            return EXIT_OK
        for result in results:
            table = Table(title=f"whole processes, {result['scene']}: {result['shots']} shots at "
                                f"{result['samples_per_pixel']} spp ({result['lens_samples'] / 1e6:.0f} M lens "
                                f"samples), {result['machine']['cores']} cores")
            for col in ("renderer", "seconds (median)", "runs", "M lens samples/s"):
                table.add_column(col, justify="right")
            table.add_row("synth render --method raytrace", f"{result['synth_median_s']:.2f}",
                          " ".join(f"{t:.2f}" for t in result["synth_s"]), f"{result['synth_mega_samples_per_s']:.0f}")
            table.add_row(f"Mitsuba 3 {result['mitsuba_variant']}", f"{result['mitsuba_median_s']:.2f}",
                          " ".join(f"{t:.2f}" for t in result["mitsuba_s"]),
                          f"{result['mitsuba_mega_samples_per_s']:.0f}")
            Console().print(table)
            print(f"synth is {result['ratio']:.1f}x faster (median of the pairs' ratios)")
        if doc is not None:
            table = Table(title="the tracer's kernel per lens sample (warm, every pixel traced)")
            for col in ("lens", "surfaces", "ns per lens sample", "over the thin lens"):
                table.add_column(col, justify="right")
            for r in doc["lens_samples"]:
                table.add_row(r["lens"], str(r["surfaces"]), f"{r['ns_per_lens_sample']:.1f}",
                              f"{r['cost_over_thin_lens']:.1f}x")
            Console().print(table)
        return EXIT_OK
    enable_compilation_cache()
    with console.status("benchmarking") as status:
        result = run_bench(repeats=args.repeats, include_compile=not args.no_compile,
                           progress=lambda msg: status.update(f"benchmarking: {msg}"))
    if args.json:
        print(json.dumps(result, indent=1))
        return EXIT_OK
    w, h = result["image_px"]
    table = Table(title=f"raytrace, {w} x {h} px ({result['scene']} {result['flat_shot']}, CoC "
                        f"{result['coc_diameter_px_flat']:.1f} px), {result['machine']['cores']} cores")
    for col in ("spp", "seconds", "tilted ChArUco s", "M lens samples/s", "with constant regions s",
                "tilted s", "RMS error"):
        table.add_column(col, justify="right")
    for r in result["raytrace"]:
        table.add_row(str(r["samples_per_pixel"]), f"{r['seconds']:.3f}", f"{r['seconds_tilted_charuco']:.3f}",
                      f"{r['mega_lens_samples_per_s']:.0f}", f"{r['seconds_constant_regions']:.3f}",
                      f"{r['seconds_tilted_constant_regions']:.3f}", f"{r['rms_error']:.2e}")
    Console().print(table)
    print("every pixel traced (the kernel's speed); with constant regions: pixels whose rays all meet one "
          f"uniform region take its value unsampled (synth.flat), {100 * result['traced_fraction']['flat']:.0f} % "
          f"/ {100 * result['traced_fraction']['tilted']:.0f} % of the pixels traced, the same image")
    table = Table(title="convolve, same shot")
    for col in ("sub-pixels", "seconds", "RMS error"):
        table.add_column(col, justify="right")
    for r in result["convolve"]:
        table.add_row(f"{r['supersampling']} x {r['supersampling']}", f"{r['seconds']:.3f}", f"{r['rms_error']:.2e}")
    Console().print(table)
    print(result["error_note"])
    if "compile_cold_s" in result:
        print(f"compilation: {result['compile_cold_s']:.2f} s cold, {result['compile_cached_s']:.2f} s from the "
              "persistent cache")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="synth", description="Thin-lens renderer whose defocus blur is known exactly. "
                                     "All lengths in millimetres.")
    parser.add_argument("--version", action="version", version=f"synth {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    def common(p):
        p.add_argument("scene", help="scene spec (TOML; schema: data_specs/schemas/scene.schema.json)")
        p.add_argument("--method", choices=["auto", "raytrace", "convolve", "mitsuba"],
                       help="render method (default: the scene's render.method, else auto); mitsuba: the "
                            "thin-lens scenes through Mitsuba 3 (pip install mitsuba), an independent renderer")
        p.add_argument("--spp", type=int, metavar="N", help="ray-tracing samples per pixel (default: the scene's)")

    r = sub.add_parser("render", help="render a scene into a stack folder",
                       description="Render SCENE into DIR: images, stack.toml, truth.json, truth maps.")
    common(r)
    r.add_argument("--out", required=True, metavar="DIR", help="output stack folder (new or empty)")
    r.add_argument("--seed", type=int, metavar="N", help="random seed (default: the scene's render.seed)")
    r.add_argument("--supersampling", type=int, metavar="S", help="convolve: sub-pixels per axis (default 4)")
    r.add_argument("--mitsuba-variant", choices=["scalar_rgb", "llvm_ad_rgb"],
                   help="method mitsuba: Mitsuba 3's variant (default: the scene's render.mitsuba_variant, else "
                        "scalar_rgb); llvm_ad_rgb is vectorised and needs libLLVM (pip install karellen-llvm-core)")
    r.add_argument("--format", choices=["png", "tiff", "float-tiff", "dng", "jpeg"],
                   help="image files (default png, 16-bit linear; dng with the mosaic effect, which requires it; "
                        "jpeg: 8-bit sRGB with EXIF, as a camera's JPEG)")
    r.add_argument("--preview", metavar="PNG", help="also write a contact sheet of the shots (sRGB, to look at)")
    r.add_argument("--force", action="store_true", help="replace a stack folder (and --preview file) that synth wrote; never other files")
    r.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    r.set_defaults(func=_render_command, prog="synth render")

    p = sub.add_parser("plan", help="show the stages, method and estimated cost without rendering")
    common(p)
    p.set_defaults(func=_plan_command, prog="synth plan")

    b = sub.add_parser("bench", help="measure render speed and accuracy (error versus seconds)")
    b.add_argument("--repeats", type=int, default=3, help="timed runs per figure; the best is kept")
    b.add_argument("--no-compile", action="store_true", help="skip the compile-time measurement")
    b.add_argument("--json", action="store_true", help="print JSON")
    b.add_argument("--against-mitsuba", action="store_true",
                   help="instead: whole processes, synth render --method raytrace against Mitsuba 3 rendering the "
                        "same scene at the same spp, PAIRS times back to back")
    b.add_argument("--plan-costs", action="store_true",
                   help="instead: synth plan's time estimates against warm renders of shipped scenes (thin and "
                        "compound lenses, several wavelengths)")
    b.add_argument("--record", metavar="DIR", help="--plan-costs or --against-mitsuba: also write the record "
                                                   "DIR/plan_costs.json or DIR/synth_vs_mitsuba.json (the "
                                                   "documentation's are in docs/validation/records)")
    b.add_argument("--scene", metavar="TOML", help="--against-mitsuba: the scene (default: the demo scene; a "
                                                   "record is always the demo's)")
    b.add_argument("--spp", type=int, nargs="+", default=[32], metavar="N",
                   help="--against-mitsuba: samples per pixel, one comparison each (default 32)")
    b.add_argument("--pairs", type=int, default=3, metavar="K", help="--against-mitsuba: process pairs (default 3)")
    b.add_argument("--mitsuba-variant", choices=["llvm_ad_rgb", "scalar_rgb"], default="llvm_ad_rgb",
                   help="--against-mitsuba: Mitsuba's variant (default llvm_ad_rgb, which needs libLLVM 20 or later: "
                        "pip install karellen-llvm-core)")
    b.set_defaults(func=_bench_command, prog="synth bench")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from lensfit.runtime.running import run_guarded

    parser = build_parser()
    args = parser.parse_args(argv)

    def known(exc: Exception):
        if isinstance(exc, InputError):
            return exc.describe(_OPTIONS), EXIT_USAGE
        return None

    return run_guarded(args.prog, lambda: args.func(args), known)


def run() -> None:
    """The ``synth`` program: :func:`main` on the command line's arguments, then the process ends
    (``lensfit.runtime.running.exit_process``)."""
    from lensfit.runtime.running import exit_process

    exit_process(main())


if __name__ == "__main__":
    run()
