"""The ``lensfit`` command line: thin; parses, calls the API, prints.

Heavy modules (JAX, OpenCV) are imported inside the commands, so ``lensfit --help`` answers
at once. One module per group of commands (``dof``, ``fit`` with ``measure``, ``capture``:
target, init and plan; ``bench``); the parser and ``main`` are here.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from lensfit import __version__
from lensfit.errors import InputError
from lensfit.cli.bench import (bench_command, bench_fit_command, bench_lenses_command, bench_measure_command,
                               bench_stages_command, bench_api_command, bench_hostile_command,
                               bench_developed_command)
from lensfit.cli.capture import init_command, plan_command, target_command
from lensfit.cli.common import (EXIT_BENCH_FAILED, EXIT_NOT_IDENTIFIABLE, EXIT_OK, EXIT_USAGE, FIT_OPTIONS, CliError,
                                diffraction_arg, input_options, jobs_arg, number_arg, pupil_arg)
from lensfit.cli.dof import dof_command
from lensfit.cli.fit import fit_command, measure_command

__all__ = ["main", "build_parser", "CliError", "EXIT_OK", "EXIT_USAGE", "EXIT_NOT_IDENTIFIABLE", "EXIT_BENCH_FAILED"]


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
    dof.add_argument("--focal-length", type=number_arg, required=True, metavar="MM",
                     help="focal length f, mm (> 0)")
    dof.add_argument("--f-number", type=number_arg, required=True, metavar="N",
                     help="f-number N (> 0)")
    dof.add_argument("--focus-distance", type=number_arg, required=True, metavar="MM",
                     help="focus distance D_s from the lens plane, mm (> focal length; 'inf' allowed)")
    dof.add_argument("--coc", type=number_arg, metavar="MM",
                     help="acceptable circle-of-confusion diameter, mm (default: sensor diagonal / 1500)")
    dof.add_argument("--sensor", metavar="NAME",
                     help="sensor format, e.g. full-frame, aps-c, micro-four-thirds (data_specs/sensor_formats.toml)")
    dof.add_argument("--pixel-pitch", type=number_arg, metavar="MM",
                     help="pixel pitch, mm, to express the CoC in pixels (default: from --sensor when known)")
    dof.add_argument("--json", action="store_true", help="print a JSON object instead of a table")
    dof.set_defaults(func=dof_command, prog="lensfit dof")

    tg = sub.add_parser("target", help="write a printable ChArUco board (PDF/SVG/PNG) and its stack.toml entry",
                        description="Lay out a ChArUco board at its true size on a sheet of paper (vector PDF or "
                                    "SVG, or a PNG raster, by --out's suffix), labelled with what board it is and "
                                    "a scale bar, and print the [[target]] entry of stack.toml that describes it. "
                                    "Print at 100 % and measure a square before use (lensfit init "
                                    "--measured-square-mm).")
    tg.add_argument("--out", required=True, metavar="FILE", help="board.pdf, board.svg or board.png")
    tg.add_argument("--paper", default="a4-landscape", metavar="SIZE",
                    help="a4, a3, a2, letter, tabloid (+ -landscape) or WxH in mm (default a4-landscape)")
    tg.add_argument("--squares", type=int, nargs=2, default=(9, 6), metavar=("COLS", "ROWS"),
                    help="squares across and down (default 9 6)")
    tg.add_argument("--square-mm", type=number_arg, metavar="MM", help="square side (default: the largest that fits)")
    tg.add_argument("--marker-mm", type=number_arg, metavar="MM", help="marker side (default 0.75 x the square)")
    tg.add_argument("--dictionary", default="DICT_5X5_100", metavar="NAME",
                    help="OpenCV ArUco dictionary (default DICT_5X5_100)")
    tg.add_argument("--dpi", type=number_arg, default=300.0,
                    help="a PNG's resolution, at least this (default 300; PDF and SVG are vector)")
    tg.add_argument("--id", default="board", help="the target's id in stack.toml (default board)")
    tg.add_argument("--entry", metavar="FILE.toml",
                    help="also write the [[target]] entry to this file (for lensfit init --target)")
    tg.add_argument("--force", action="store_true", help="replace an existing board this program wrote")
    tg.set_defaults(func=target_command, prog="lensfit target")

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
    it.add_argument("--measured-square-mm", type=number_arg, metavar="MM",
                    help="a printed square's side as measured with a ruler: the target's square_mm and marker_mm "
                         "are scaled by it over the square_mm it was drawn with (printers scale by a few per cent)")
    it.add_argument("--pixel-pitch", type=number_arg, metavar="MM", help="sensor pixel pitch, mm (overrides the EXIF)")
    it.add_argument("--sensor-width", type=number_arg, metavar="MM",
                    help="sensor active width, mm (the pitch is this / image width)")
    it.add_argument("--sensor", metavar="NAME", help="a sensor format of data_specs/sensor_formats.toml")
    it.add_argument("--settings", default="exif", choices=["exif", "per-image", "one"],
                    help="setting labels: by the EXIF f-number and focus distance (default), one per image, or one")
    it.add_argument("--prefer", default="raw", choices=["raw", "jpeg"],
                    help="which file of a RAW + JPEG pair to list (default raw: linear, no tone curve)")
    it.add_argument("--out", metavar="FILE", help="manifest to write (default PHOTOS_DIR/stack.toml)")
    it.add_argument("--force", action="store_true", help="replace a stack.toml lensfit init wrote")
    input_options(it, outside=False, jobs=False)
    it.set_defaults(func=init_command, prog="lensfit init")

    pl = sub.add_parser("plan", help="where to put the target and how many shots for a requested accuracy",
                        description="Plan a capture for a lens guess: the usable target distances (the board fits, "
                                    "its squares are detectable, the blur leaves them readable), shots spread evenly in "
                                    "inverse distance over them, and the Cramer-Rao bound of f, N and the focus "
                                    "distance against the number of shots; the smallest number reaching --goal.")
    pl.add_argument("--focal-length", type=number_arg, required=True, metavar="MM", help="focal length guess, mm")
    pl.add_argument("--f-number", type=number_arg, required=True, metavar="N", help="f-number of the capture")
    pl.add_argument("--focus-distance", type=number_arg, required=True, metavar="MM",
                    help="focus distance from the lens, mm ('inf' allowed)")
    pl.add_argument("--sensor", metavar="NAME", help="sensor format with a pixel grid (data_specs/sensor_formats.toml)")
    pl.add_argument("--pixel-pitch", type=number_arg, metavar="MM", help="pixel pitch, mm")
    pl.add_argument("--width-px", type=int, metavar="PX", help="image width, px")
    pl.add_argument("--height-px", type=int, metavar="PX", help="image height, px")
    pl.add_argument("--target", metavar="FILE.toml",
                    help="the board's [[target]] entry (lensfit target --entry); default: lensfit target's default board")
    pl.add_argument("--goal", type=number_arg, default=1.0, metavar="PCT",
                    help="95%% half-interval to reach on f, N and focus distance, per cent (default 1)")
    pl.add_argument("--max-shots", type=int, default=48, metavar="N", help="largest capture considered (default 48)")
    pl.add_argument("--edge-sigma-px", type=number_arg, default=0.05, metavar="PX",
                    help="blur measurement noise per edge, px (default 0.05)")
    pl.add_argument("--edge-sigma-rel", type=number_arg, default=2.0, metavar="PCT",
                    help="and its part proportional to the blur, per cent (default 2)")
    pl.add_argument("--calibration-sigma", type=number_arg, default=0.1, metavar="PCT",
                    help="1-sigma of the calibrated focal length in px, per cent (default 0.1)")
    pl.add_argument("--shot-list", metavar="FILE", help="also write the plan as a one-page shot list to print "
                                                        "(.pdf, .svg or .png): distances, how to turn the board, "
                                                        "boxes to tick, the checklist")
    pl.add_argument("--force", action="store_true", help="replace a --shot-list this program wrote")
    pl.add_argument("--json", action="store_true", help="print the plan as JSON")
    pl.set_defaults(func=plan_command, prog="lensfit plan")

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
    input_options(m)
    m.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    m.set_defaults(func=measure_command, prog="lensfit measure")

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
    ft.add_argument("--blur-floor", type=number_arg, metavar="PX",
                    help="fix the blur floor (px) instead of fitting it per setting")
    ft.add_argument("--pupil-magnification", type=pupil_arg, metavar="P|LO:HI",
                    help="pupil magnification P (exit / entrance pupil diameter) of a thick lens: a value to assume, "
                         "or a range LO:HI (a prior whose 95%% interval it is; widens f and N honestly). Default: "
                         "stack.toml's [lens] pupil_magnification, else fitted from two or more focus settings, else "
                         "carried over the spread of photographic lenses with a warning")
    ft.add_argument("--focusing", choices=("unknown", "unit", "internal"), default=None,
                    help="how the lens focuses: unit (the whole lens moves: settings share f and P, and a focus bracket "
                         "fits P), internal (a group inside moves: f changes with focus) or unknown; default: "
                         "stack.toml's [lens] focusing, else unknown (each setting fitted by itself)")
    ft.add_argument("--widest-f-number", type=number_arg, default=None, metavar="N",
                    help="the lens's widest f-number, its full aperture (1:1.4 on the barrel is 1.4): each setting then "
                         "carries the spread of real designs stopped down as far as it is, narrower than wide open's. "
                         "Default: stack.toml's [lens] widest_f_number (lensfit init copies EXIF MaxApertureValue), "
                         "else the spread wide open")
    ft.add_argument("--ideal-lens", action=argparse.BooleanOptionalAction, default=None,
                    help="the lens has no aberrations (a renderer's thin-lens camera): report the blur's own f-number. "
                         "Default: stack.toml's [lens] ideal, else a real lens: the nominal f-number (EFL / entrance "
                         "pupil) with the spread of real designs' blur against it carried in its interval")
    ft.add_argument("--processed", choices=("model", "refuse", "report"), default="model",
                    help="where images were developed (EXIF names a raw developer or a camera's JPEG engine), "
                         "sharpened (halos on the edges) or hold a tone curve their encoding does not undo: model "
                         "(default) reads the blur through a tone curve and unsharp mask fitted to the edges, the "
                         "f-number's interval carrying their uncertainty, and refuses it where they do not hold the "
                         "images; refuse the f-number outright, naming the cause and the fix; or report it with a "
                         "warning")
    ft.add_argument("--field-curvature", choices=("auto", "on", "off"), default="auto",
                    help="a real lens focuses the edge of the field at another distance than the centre: per setting, "
                         "the in-focus inverse distance 1/X + kappa tan^2(field angle), the reported X on the axis; "
                         "auto (default) fits kappa and keeps it where it differs from 0 by 3 sigma, on keeps it "
                         "always, off assumes 0 (a thin lens)")
    ft.add_argument("--spot-shape", choices=("auto", "shaped", "disk"), default="auto",
                    help="where an edge's spot was read both ways, the blur reading to fit: shaped (its second "
                         "moment through the spot's shape: a real lens's rims and cores), disk (the uniform disk's), "
                         "or auto (default): shaped, unless the Airy pattern would reach 0.5 px and the images were "
                         "not tested for it")
    ft.add_argument("--diffraction", type=diffraction_arg, nargs="?", const=550.0, default="auto",
                    metavar="NM|auto|off",
                    help="diffraction in the blur readings (the Airy pattern of each setting's working f-number): "
                         "NM models it at this effective wavelength (bare: 550 nm); auto (default) models it at "
                         "550 nm where the lens is stopped down far enough for the pattern to reach half a pixel "
                         "and the small blurs' edges fit better with it (a photograph, not a geometric render); "
                         "off never. Modelling measures again once to three times (about 3-5x the measuring "
                         "time); where the auto test runs it reads up to 16 edges again through the Airy model")
    ft.add_argument("--pixel-pitch", type=number_arg, metavar="MM",
                    help="pixel pitch, mm (for samples without it, e.g. a CSV of your own)")
    ft.add_argument("--focal-length-px", type=number_arg, metavar="PX",
                    help="calibrated focal length in px (overrides the samples file's; for samples without one)")
    ft.add_argument("--json", action="store_true", help="print the results JSON instead of tables")
    ft.add_argument("--force", action="store_true", help="replace existing output files that lensfit wrote")
    input_options(ft)
    ft.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    ft.set_defaults(func=fit_command, prog="lensfit fit")

    bs = sub.add_parser("bench", help="run a benchmark suite and write its report",
                        description="Run a suite of data_specs/bench/ (scenes x render quality x noise x "
                                    "estimators x solver settings x seeds): render, measure and fit each case, then "
                                    "write results.json, report.md and a self-contained report.html to --out. "
                                    "Finished cases are cached: --resume continues an interrupted run.")
    bs.add_argument("--suite", default="quick", metavar="NAME", help="quick (default), standard, hard, or a .toml path")
    bs.add_argument("--out", required=True, metavar="DIR", help="output folder (new or empty, unless --resume)")
    bs.add_argument("--jobs", type=int, default=1, metavar="N", help="parallel processes or Dask workers (default 1)")
    bs.add_argument("--resume", action="store_true", help="continue a run in --out, keeping finished cases")
    bs.add_argument("--seeds", metavar="LIST",
                    help="the seeds to run instead of the suite's, e.g. 0-9 or 0,1,5: more seeds, more cases to "
                         "tell the intervals' coverage by; with --resume the cases already finished are kept "
                         "(--seeds 0-9 on a run of seeds 0-3 runs 4-9 only)")
    bs.add_argument("--executor", default="local", metavar="KIND",
                    help="local (process pool, default), dask (a local Dask cluster) or dask://HOST:PORT")
    bs.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    bs.add_argument("--allow-fail", action="store_true",
                    help="exit 0 even when estimates miss the suite's tolerances (default: exit status 4)")
    bs.add_argument("--record", metavar="DIR",
                    help="also write the suite's record (DIR/SUITE.json: headline figures, date, command) that the "
                         "documentation's validation page and the README's accuracy table are made from, replacing "
                         "the suite's earlier record there (e.g. docs/validation/records)")
    bs.set_defaults(func=bench_command, prog="lensfit bench")

    bf = sub.add_parser("bench-fit", help="accuracy of f, N, focus distance and honesty of sigma under noise",
                        description="Measure and fit a rendered STACK (with truth.json) clean and with seeded "
                                    "photon + read noise; report errors, observed scatter and stated sigma.")
    bf.add_argument("--stack", required=True, metavar="DIR", help="a stack rendered by synth (linear PNGs)")
    bf.add_argument("--seeds", type=int, default=5, help="noise draws (default 5)")
    bf.add_argument("--full-well", type=number_arg, default=20000.0, metavar="E", help="electrons at white (20000)")
    bf.add_argument("--read-noise", type=number_arg, default=5.0, metavar="E", help="read noise, electrons (5)")
    bf.add_argument("--estimator", default="edge", metavar="NAME", help="blur estimator (edge)")
    bf.add_argument("--json", action="store_true", help="print JSON")
    bf.set_defaults(func=bench_fit_command, prog="lensfit bench-fit")

    bl = sub.add_parser("bench-lenses", help="thin- and thick-lens fits on stacks ray traced through real lenses",
                        description="Render the demo calibration stack through every shipped compound lens "
                                    "(data_specs/lenses) at two focus distances, and fit it as a thin lens (one setting), "
                                    "as a thick lens with P given, and as a thick lens with P fitted from the bracket.")
    bl.add_argument("--lens", action="append", metavar="NAME", help="only this design (repeatable)")
    bl.add_argument("--spp", type=int, default=64, help="ray-tracing samples per pixel (default 64)")
    bl.add_argument("--f-number", type=number_arg, default=11.0, metavar="N",
                    help="f-number of every shot (default 11; faster than a design opens to is refused)")
    bl.add_argument("--wavelengths", type=number_arg, nargs="+", metavar="NM",
                    help="render grey through these wavelengths (glass dispersion: longitudinal and lateral colour); "
                         "only the designs whose glasses are known (default: the d line alone)")
    bl.add_argument("--scale", type=number_arg, default=1.0, metavar="K",
                    help="image size as a fraction of the demo's 1200 x 800 px (default 1; 0.5 renders 4x faster, "
                         "with calibrations and so P about half as precise)")
    bl.add_argument("--designs", choices=("shipped", "optiland", "rayoptics"), default="shipped",
                    help="shipped: the designs in data_specs/lenses (default); optiland: optiland's all-spherical "
                         "sample objectives, which lensfit does not ship (needs optiland: the test extra); "
                         "rayoptics: the all-spherical photographic objectives among rayoptics's sample lens files "
                         "(CODE V, Zemax and its own; needs rayoptics, which make setup installs)")
    bl.add_argument("--wide-open", action="store_true",
                    help="each design at its own f-number (the far setting; the near one two stops down) instead of "
                         "--f-number")
    bl.add_argument("--bracket", choices=("wide", "narrow"), default="wide",
                    help="wide: the near setting at a sixth of the far one's distances (inverse focus distances "
                         "1/(8 f) apart, P fitted to a few per cent; default); narrow: at half (1/(40 f) apart, too "
                         "narrow to fit P)")
    bl.add_argument("--focusing", choices=("unit", "internal"), default="unit",
                    help="unit: the whole lens moves (default); internal: the group behind the stop (else the one in "
                         "front of it) moves, the sensor fixed, so f, N and P change per setting, and the bracket "
                         "is fitted setting by setting")
    bl.add_argument("--field", choices=("demo", "design"), default="demo",
                    help="demo: every design at the demo's angle of view (9.8 degrees half-diagonal; default); "
                         "design: optiland's and rayoptics's designs each at its own half field of view where wider "
                         "(up to 35 degrees), the sensor, pixels and boards widened with it")
    bl.add_argument("--keep", metavar="DIR", help="write the rendered stacks to DIR/NAME and keep them")
    bl.add_argument("--reuse", metavar="DIR", help="render nothing: measure and fit again the stacks --keep wrote to DIR")
    bl.add_argument("--record", metavar="DIR", help="also write the record DIR/lenses.json the validation page "
                                                   "shows (docs/validation/records), one per variant: optiland's "
                                                   "designs wide open at --scale 0.5 lenses.json; the shipped "
                                                   "designs, a given --f-number, a narrow bracket, internal "
                                                   "focusing, --field design and another --scale name it further "
                                                   "(lenses_shipped_f11.json, lenses_f5.6_narrow.json, "
                                                   "lenses_scale1.json, ...)")
    bl.add_argument("--json", action="store_true", help="print JSON")
    bl.set_defaults(func=bench_lenses_command, prog="lensfit bench-lenses")

    bm = sub.add_parser("bench-measure", help="accuracy and time per edge of the blur estimators",
                        description="Benchmark: slanted edges rendered by synth at several CoC diameters and "
                                    "noise levels; the edge estimator's relative bias on exact (analytic) edges "
                                    "against the fit's error budget; optionally both estimators on a rendered "
                                    "STACK with truth.")
    bm.add_argument("--stack", metavar="DIR", help="also run every estimator on this rendered stack")
    bm.add_argument("--draws", type=int, default=3, help="noise draws per case (default 3)")
    bm.add_argument("--json", action="store_true", help="print JSON")
    bm.set_defaults(func=bench_measure_command, prog="lensfit bench-measure")

    bs = sub.add_parser("bench-stages", help="seconds per stage of measure + fit, cold and warm, by size",
                        description="Benchmark: seconds per stage (read, detect, calibrate, measure, fit, "
                                    "uncertainty) of a stack, cold (fresh process) and warm, for its first K "
                                    "images and enlarged X times; the whole `lensfit fit` against OpenCV's own "
                                    "detect + calibrate of the same files, as a ratio.")
    bs.add_argument("stack", metavar="STACK", help="a stack folder (stack.toml) with ChArUco targets")
    bs.add_argument("--images", type=int, nargs="+", default=[3, 6], metavar="K",
                    help="also time the first K images (default 3 6; the whole stack always)")
    bs.add_argument("--scale", type=number_arg, nargs="+", default=[1.0, 2.0], metavar="X",
                    help="enlargements of the whole stack (bilinear, pitch / X; default 1 2)")
    bs.add_argument("--repeat", type=int, default=3, metavar="K",
                    help="whole-process pairs (lensfit fit, OpenCV) run back to back; medians (default 3)")
    bs.add_argument("--warm-runs", type=int, default=3, metavar="K",
                    help="warm calls per configuration after the cold one; each stage's median (default 3)")
    bs.add_argument("--jobs", type=jobs_arg, nargs="+", default=[1], metavar="N",
                    help="also run the whole `lensfit fit` at each --jobs N (e.g. 1 2) and report the speed-up and "
                         "whether the results are identical (default 1)")
    bs.add_argument("--shots", type=int, nargs="+", default=[], metavar="N",
                    help="whole-stack rows of N images at each --scale, one per N (the stack's own again, in turn, "
                         "where it has fewer; e.g. 12 30 at --scale 6.85: 12- and 30-shot 45 MP stacks from the "
                         "demo; default: the stack's own count)")
    bs.add_argument("--record", metavar="DIR", help="also write the record DIR/stages.json the validation page "
                                                   "shows (docs/validation/records)")
    bs.add_argument("--json", action="store_true", help="print JSON")
    bs.set_defaults(func=bench_stages_command, prog="lensfit bench-stages")

    ba = sub.add_parser("bench-api", help="the README's Python example against lensfit fit, fresh processes",
                        description="Benchmark: a fresh `lensfit fit STACK` process against a fresh Python process "
                                    "running the README's measure_and_fit on the same stack, alternating pairs after "
                                    "a warm-up; the median of the pairs' ratios.")
    ba.add_argument("stack", metavar="STACK", help="a stack folder (e.g. out/demo after make demo)")
    ba.add_argument("--pairs", type=int, default=3, metavar="N", help="alternating pairs (default 3)")
    ba.add_argument("--record", metavar="DIR",
                    help="also write the figures to DIR/api_vs_cli.json for the documentation's validation page "
                         "(e.g. docs/validation/records)")
    ba.add_argument("--json", action="store_true", help="print JSON")
    ba.set_defaults(func=bench_api_command, prog="lensfit bench-api")

    bh = sub.add_parser("bench-hostile", help="hostile inputs at scale: exit status, time and peak memory of each",
                        description="Benchmark: inputs a hostile or careless user could give, with large counts "
                                    "(PNG chunk bombs, 100,000 image entries, a million-row samples CSV, TOML nested "
                                    "100,000 deep, 10,000 photos, a sparse 4 GiB output), each run in a fresh process "
                                    "as a user would run it; each case's exit status, seconds and peak memory. Exit "
                                    "4 where a case fails (wrong status, not one line, over 60 s or 1 GiB).")
    bh.add_argument("--only", nargs="+", metavar="CASE", help="run only these cases (default: all)")
    bh.add_argument("--record", metavar="DIR",
                    help="also write the table to DIR/hostile.json for the documentation's validation page "
                         "(e.g. docs/validation/records)")
    bh.add_argument("--json", action="store_true", help="print JSON")
    bh.set_defaults(func=bench_hostile_command, prog="lensfit bench-hostile")

    bd = sub.add_parser("bench-developed", help="developed JPEGs from raw developers: f, N, focus against the truth",
                        description="Benchmark: the camera-raw scene's DNGs developed by RawTherapee and darktable "
                                    "(their default profiles; Debian packages rawtherapee and darktable, reported "
                                    "as missing where not installed) into JPEGs, drafted by lensfit init and fitted; "
                                    "the DNGs are the control. Exit 4 where a case fails.")
    bd.add_argument("--developers", nargs="+", choices=["rawtherapee", "darktable"],
                    default=["rawtherapee", "darktable"], help="which developers (default: both)")
    bd.add_argument("--f-numbers", nargs="+", type=float, metavar="N", default=[11.0, 5.6],
                    help="render the scene at these f-numbers, the exposure time scaled to the same light "
                         "(default: 11 5.6)")
    bd.add_argument("--keep", metavar="DIR", help="keep the rendered and developed stacks in DIR (a new folder)")
    bd.add_argument("--record", metavar="DIR",
                    help="also write the table to DIR/developed.json for the documentation's validation page "
                         "(e.g. docs/validation/records)")
    bd.add_argument("--json", action="store_true", help="print JSON")
    bd.set_defaults(func=bench_developed_command, prog="lensfit bench-developed")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from lensfit.runtime.running import run_guarded

    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv

    def known(exc: Exception):
        if isinstance(exc, CliError):
            return str(exc), exc.code
        if isinstance(exc, InputError):  # input errors the command did not map itself
            return exc.describe(FIT_OPTIONS), EXIT_USAGE
        return None

    return run_guarded(args.prog, lambda: args.func(args), known)


def run() -> None:
    """The ``lensfit`` program: :func:`main` on the command line's arguments, then the process
    ends (``lensfit.runtime.running.exit_process``)."""
    from lensfit.runtime.running import command_process, exit_process

    command_process()
    exit_process(main())


if __name__ == "__main__":
    run()
