"""``lensfit dof``: the depth-of-field calculator."""

from __future__ import annotations

import argparse
import json
import math

from lensfit.errors import InputError
from lensfit.cli.common import EXIT_OK, CliError, fail_input, fmt_mm

_DOF_OPTIONS = {
    "focal_length_mm": "--focal-length",
    "f_number": "--f-number",
    "focus_distance_mm": "--focus-distance",
    "acceptable_coc_diameter_mm": "--coc",
    "sensor": "--sensor",
    "pixel_pitch_mm": "--pixel-pitch",
}


#: The largest acceptable circle of confusion taken (mm): large-format film's is about 0.2 mm; a
#: value far above it is a unit slip (micrometres typed for millimetres).
MAX_COC_MM = 1.0


def dof_command(args: argparse.Namespace) -> int:
    from lensfit import optics
    from lensfit.io.sensors import sensor_format

    try:
        fmt = sensor_format(args.sensor) if args.sensor else None
        pitch = args.pixel_pitch if args.pixel_pitch is not None else (fmt.pixel_pitch_mm if fmt else None)
        if args.pixel_pitch is not None and not (args.pixel_pitch > 0 and math.isfinite(args.pixel_pitch)):
            raise InputError("pixel_pitch_mm", args.pixel_pitch, "> 0 mm and finite")
        if args.coc is not None:
            if args.coc > MAX_COC_MM:
                raise CliError(f"--coc must be at most {MAX_COC_MM:g} mm, got {args.coc:g}: an acceptable circle of "
                               "confusion is a small fraction of a mm (0.005-0.2 mm from phones to large format); "
                               f"micrometres are given as mm, e.g. 30 um is --coc {args.coc / 1000:g}")
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
        raise fail_input(exc, _DOF_OPTIONS) from None

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

    table = Table(title=f"Depth of field: {f:g} mm f/{N:g} focused at {fmt_mm(D)} from the lens",
                  show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("near limit", fmt_mm(near))
    table.add_row("far limit", fmt_mm(far) + ("  (focus beyond hyperfocal)" if not math.isfinite(far) else ""))
    table.add_row("depth of field (exact)", fmt_mm(dof))
    if dof_approx is not None:
        table.add_row("depth of field (2NCD²/f²)", fmt_mm(dof_approx))
    table.add_row("hyperfocal distance", fmt_mm(hyper))
    coc_px = f" = {coc / pitch:.2f} px at {pitch * 1000:g} µm pitch" if pitch else ""
    table.add_row("acceptable CoC diameter", f"{coc * 1000:.1f} µm{coc_px}")
    table.add_row("  from", coc_source)
    table.add_row("aperture diameter", fmt_mm(aperture))
    table.add_row("sensor distance (lens to sensor)", fmt_mm(s))
    table.add_row("focus distance from sensor plane", fmt_mm(from_sensor))
    table.add_row("magnification at focus", f"{mag:.4g}")
    if fmt is not None:
        fov = result["field_of_view_deg"]
        table.add_row("field of view (h x v, diag)",
                      f"{fov['horizontal']:.1f}° x {fov['vertical']:.1f}°, {fov['diagonal']:.1f}°")
        table.add_row("crop factor", f"{result['crop_factor']:.2f} ({fmt.name})")
    Console().print(table)
    return EXIT_OK
