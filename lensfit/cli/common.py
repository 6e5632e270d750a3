"""What every ``lensfit`` command shares: exit codes, the one-line error, option parsers and
the option-name maps that make library errors name what the user typed."""

from __future__ import annotations

import argparse
import math


#: Exit codes.
EXIT_OK = 0
EXIT_USAGE = 2  # bad arguments or input files (argparse uses 2 too)
EXIT_NOT_IDENTIFIABLE = 3  # the fit ran, but some parameter cannot be determined from the data
EXIT_BENCH_FAILED = 4  # a benchmark ran, but some case missed its tolerance (lensfit bench)

# Library argument names -> the options a user typed, so that errors name what they wrote.
_MEASURE_OPTIONS = {"estimator": "--estimator", "setting": "setting"}
FIT_OPTIONS = {**_MEASURE_OPTIONS, "pixel_pitch_mm": "--pixel-pitch", "focal_length_px": "--focal-length-px",
                "loss": "--loss", "blur_floor_px": "--blur-floor", "pupil_magnification": "--pupil-magnification",
                "field_curvature": "--field-curvature", "spot_shape": "--spot-shape",
                "widest_f_number": "--widest-f-number", "focusing": "--focusing", "ideal_lens": "--ideal-lens"}

class CliError(Exception):
    """A one-line message for the user and an exit code."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def fail_input(exc, options: dict[str, str]) -> CliError:
    """Turn a library InputError into a CLI error naming the option."""
    return CliError(exc.describe(options))


def fmt_mm(x: float | None) -> str:
    if x is None or math.isinf(x):
        return "infinity"
    if abs(x) >= 1000:
        return f"{x:,.1f} mm ({x / 1000:.3f} m)"
    return f"{x:.3f} mm" if abs(x) < 100 else f"{x:.1f} mm"


def max_pixels_arg(args: argparse.Namespace) -> int:
    mp = args.max_megapixels
    if not (math.isfinite(mp) and mp > 0):
        raise CliError(f"--max-megapixels must be a positive number, got {mp:g}")
    return int(mp * 1e6)


def progress_bar(console, enabled: bool):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), console=console, disable=not console.is_terminal and not enabled)


def number_arg(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def diffraction_arg(text: str) -> float | str:
    """``--diffraction``: a wavelength in nm, ``auto`` or ``off``."""
    if text in ("auto", "off"):
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a wavelength in nm (e.g. 550), auto or off, got {text!r}") from None


def pupil_arg(text: str) -> float | tuple[float, float]:
    """``--pupil-magnification``: a number, or ``LO:HI``."""
    try:
        if ":" in text:
            lo, hi = text.split(":", 1)
            return float(lo), float(hi)
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or LO:HI, got {text!r}") from None


def jobs_arg(text: str) -> int:
    """--jobs: a whole number of threads, 1 to ``lensfit.runtime.parallel.MAX_JOBS``."""
    from lensfit.runtime.parallel import MAX_JOBS

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}: a whole number of images at once, e.g. 2") from None
    if not 1 <= value <= MAX_JOBS:
        raise argparse.ArgumentTypeError(f"got {value}: from 1 to {MAX_JOBS}")
    return value


def input_options(p: argparse.ArgumentParser, outside: bool = True, jobs: bool = True) -> None:
    """Options on reading a stack: the pixel budget and reading outside the stack folder."""
    from lensfit.io.limits import DEFAULT_MAX_MEGAPIXELS

    p.add_argument("--max-megapixels", type=number_arg, default=DEFAULT_MAX_MEGAPIXELS, metavar="MP",
                   help=f"refuse images larger than this, checked from the file header before decoding "
                        f"(default {DEFAULT_MAX_MEGAPIXELS:g})")
    if jobs:
        p.add_argument("--jobs", type=jobs_arg, default=None, metavar="N",
                       help="images read and searched for targets at once, in threads (default: the cores; the "
                            "results are the same whatever N is)")
    if outside:
        p.add_argument("--allow-outside-stack", action="store_true",
                       help="read image files that stack.toml names outside the stack folder (refused by default)")
