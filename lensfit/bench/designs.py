"""The f-number a real lens's blur shows against the one it is sold by: a survey of published designs.

A lens's f-number is its paraxial focal length over its paraxial entrance-pupil diameter, EFL/EPD
(what the aperture ring says). What a blur-versus-depth fit measures is the cone of the real
rays: the second moment of the defocused spot grows with the defocus as the real rays' spread of
angles, which pupil aberrations (the real entrance pupil is not the paraxial one), the
non-paraxial angles of a fast cone and the real best focus move away from EFL/EPD; and the
sensor at the real best focus, off the paraxial image, moves the focal length a calibration
reads. This survey traces, for every all-spherical objective in optiland's sample library, every
design lensfit ships and rayoptics's photographic sample objectives, the real rays of the axial
point (``synth.lens``, checked against optiland and rayoptics in the tests) through focus, fits
the circle-of-confusion V to the exact second-moment diameters, and reports the f-number that V
gives (``N_effective``, the pupil magnification known) over EFL/EPD, and the focal length read
from the best focus over EFL, wide open and one to three stops down. ``lensfit.fitting.nominal``
carries their spreads into the reported f-number, focal length and pupil magnification.

Run ``python -m lensfit.bench.designs`` to print the table, ``--write`` to store it in
``data_specs/f_number_survey.toml`` (the table the prior's documentation cites). Needs optiland
(the test extra installs it) and rayoptics (``make setup`` installs it).
"""

from __future__ import annotations

import argparse
import inspect
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Focus distance of the survey, in focal lengths (a portrait distance; the ratio changes little
#: with it: see :func:`effective_ratio`'s ``x_over_f``).
X_OVER_F = 40.0
#: Stops below full aperture surveyed.
STOPS = (0, 1, 2, 3)
#: The distances of the through-focus sweep, as shares of the focus distance: both sides of focus,
#: far enough that the V's slopes dominate the floor.
SWEEP = (0.75, 1.4, 15)
SURVEY_NAME = "f_number_survey.toml"


@dataclass(frozen=True)
class Row:
    design: str
    source: str
    efl_mm: float
    pupil_magnification: float
    f_number: float  # EFL / EPD, paraxial
    stops_down: int
    ratio: float  # N_effective / (EFL / EPD)
    focal_ratio: float  # the focal length a calibration reads / EFL


def from_optiland(lens):
    """Our prescription of an optiland lens (spherical surfaces only; None otherwise), at its
    primary wavelength, with its f-number (paraxial EFL/EPD): (prescription, f-number). The clear
    apertures are optiland's (the paraxial marginal and chief rays' heights at full field): where
    the real marginal rays of a fast design outrun them, the axial beam is cut, as in the lens."""
    from synth.lens.prescription import Prescription, Surface

    lens.update_paraxial()  # the clear apertures: paraxial marginal plus chief ray heights
    surfaces = lens.surface_group.surfaces
    wavelength = lens.primary_wavelength
    wavelength = float(getattr(wavelength, "value", wavelength))
    z = [float(np.ravel(np.asarray(s.geometry.cs.z))[0]) for s in surfaces]
    rows = []
    for i in range(1, len(surfaces) - 1):
        s = surfaces[i]
        kind = type(s.geometry).__name__
        if kind not in ("StandardGeometry", "Plane") or float(getattr(s.geometry, "k", 0.0) or 0.0) != 0.0:
            return None
        radius = float(np.ravel(np.asarray(s.geometry.radius))[0])
        radius = radius if math.isfinite(radius) else math.inf
        n = float(np.ravel(np.asarray(s.material_post.n(wavelength)))[0])
        thickness = z[i + 1] - z[i] if i + 1 < len(surfaces) - 1 else 0.0
        semi = float(np.ravel(np.asarray(s.semi_aperture))[0])
        if math.isfinite(radius):
            semi = min(semi, 0.999 * abs(radius))
        rows.append(Surface(radius, thickness, n, semi, bool(s.is_stop)))
    if sum(r.stop for r in rows) != 1:
        return None
    rows[-1] = Surface(rows[-1].radius_mm, 0.0, 1.0, rows[-1].semi_aperture_mm, rows[-1].stop)
    return Prescription("optiland", tuple(rows)), float(lens.paraxial.FNO())


#: rayoptics's sample files that hold photographic objectives, relative to its package folder
#: (the others are telescopes, mirrors, relays, test surfaces, or aspheric designs, which synth's
#: tracer does not take): a double Gauss f/2, Sasian's triplet f/4, a patent's 50 mm f/4.5 and a
#: landscape lens f/10.
RAYOPTICS_SAMPLES = ("codev/tests/ag_dblgauss.seq", "models/Sasian Triplet.roa",
                     "zemax/tests/US00583336-2-scaled.zmx", "codev/tests/landscape_lens.seq")


def from_rayoptics(opm, name: str):
    """Our prescription of a rayoptics optical model (spherical refracting surfaces only, a stop
    among them; None otherwise), at its central wavelength, with its f-number (rayoptics's
    paraxial EFL/EPD): (prescription, f-number). The clear apertures are the ones rayoptics sets
    from the beams of the design's fields (a file may leave some unset); the stop is set to the
    design's entrance pupil, and a design whose paraxial data ours do not reproduce (EFL, pupil
    magnification, back focus: a folded or decentred one) is None too. Sets ``opm``'s apertures."""
    from synth.lens.prescription import Prescription, Surface, paraxial

    sm = opm["seq_model"]
    fod = opm["analysis_results"]["parax_data"].fod
    wavelength = float(opm["optical_spec"]["wvls"].central_wvl)
    if sm.stop_surface is None or not (fod.efl > 0 and fod.bfl > 0):
        return None
    sm.set_clear_apertures()
    rows = []
    for k in range(1, len(sm.ifcs) - 1):
        ifc, gap = sm.ifcs[k], sm.gaps[k]
        if type(getattr(ifc, "profile", None)).__name__ != "Spherical":
            return None
        cv = float(ifc.profile.cv)
        radius = math.inf if cv == 0.0 else 1.0 / cv
        semi = float(ifc.surface_od())
        if math.isfinite(radius):
            semi = min(semi, 0.999 * abs(radius))
        rows.append(Surface(radius, float(gap.thi), float(gap.medium.rindex(wavelength)), semi, k == sm.stop_surface))
    rows[-1] = Surface(rows[-1].radius_mm, 0.0, 1.0, rows[-1].semi_aperture_mm, rows[-1].stop)
    f_number = float(fod.fno)
    rx = Prescription(name, tuple(rows)).with_f_number(f_number)
    ours = paraxial(rx)
    theirs = (fod.efl, fod.exp_radius / fod.enp_radius, fod.bfl)
    if not all(math.isclose(a, b, rel_tol=1e-6) for a, b in
               zip((ours.efl_mm, ours.pupil_magnification, ours.bfl_mm), theirs)):
        return None
    return rx, f_number


def read_rayoptics(path: Path):
    """rayoptics's optical model of a lens file it reads: .roa (its own), .seq (CODE V), .zmx (Zemax)."""
    import logging

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from rayoptics.codev import cmdproc
        from rayoptics.gui.roafile import open_roa
        from rayoptics.zemax import zmxread

        # Its readers log every line they read to files in the working directory
        # (cv_cmd_proc.log, zmx_read_lens.log): a benchmark writes nothing where it is run.
        for reader in (cmdproc, zmxread):
            for handler in [h for h in reader.logger.handlers if isinstance(h, logging.FileHandler)]:
                reader.logger.removeHandler(handler)

        suffix = path.suffix.lower()
        if suffix == ".roa":
            return open_roa(path)
        return (cmdproc.read_lens(path) if suffix == ".seq" else zmxread.read_lens_file(path))[0]


def rayoptics_objectives():
    """rayoptics's all-spherical sample objectives (``RAYOPTICS_SAMPLES``): (name, prescription,
    f-number, the file it came from, its half field of view in degrees: the object angle its file
    states, or the angle of the image height it states; None where it states an object height)."""
    import rayoptics

    root = Path(rayoptics.__file__).parent
    for rel in RAYOPTICS_SAMPLES:
        name = Path(rel).stem.replace(" ", "_")
        opm = read_rayoptics(root / rel)
        got = from_rayoptics(opm, name)
        if got is not None:
            fov = opm["optical_spec"]["fov"]
            efl = opm["analysis_results"]["parax_data"].fod.efl
            field = (float(fov.value) if fov.key[1] == "angle" else
                     math.degrees(math.atan(float(fov.value) / efl)) if fov.key[0] == "image" else None)
            yield name, got[0], got[1], f"rayoptics/{rel}", field


def effective_ratio(rx, f_number: float, x_over_f: float = X_OVER_F, grid: int = 201) -> float:
    """N_effective / (EFL/EPD) of ``rx`` stopped to ``f_number``: :func:`design_ratios`'s first."""
    return design_ratios(rx, f_number, x_over_f, grid)[0]


def design_ratios(rx, f_number: float, x_over_f: float = X_OVER_F, grid: int = 201) -> tuple[float, float]:
    """What a blur-versus-depth fit reads from ``rx`` stopped to ``f_number``, focused (best
    focus, least RMS spot) at ``x_over_f`` focal lengths from its entrance pupil, over the
    paraxial values: (N_effective / (EFL/EPD), f_read / EFL).

    ``S``, the pinhole distance a calibration measures, is exit-pupil-to-sensor over P with the
    sensor at the real best focus. ``N_effective``: the V ``c = K |1/D - 1/X|`` (with a floor in
    quadrature) fitted to the exact second-moment diameters ``4 sigma_x`` of the axial point's
    real-ray spots gives ``A = K / S``, and the ratio is ``EPD / A``. ``f_read`` is the focal
    length the fit's paraxial relation ``1/S = 1/f - 1/(P X)`` gives from that ``S``: where
    spherical aberration puts the best focus off the paraxial image, it moves ``S`` and so the
    f read, by the same share at every focus distance of a bracket (so no bracket can see it)."""
    from scipy.optimize import least_squares

    from synth.lens.focus import axial_rays, best_focus_image_z, disk_grid
    from synth.lens.prescription import paraxial, trace

    rx = rx.with_f_number(f_number)
    para = paraxial(rx)
    z_ep, epd = para.entrance_pupil_z_mm, para.entrance_pupil_diameter_mm
    x = x_over_f * para.efl_mm
    z_sensor = best_focus_image_z(rx, z_ep - x)
    s_px = (z_sensor - para.exit_pupil_z_mm) / para.pupil_magnification
    u, v = disk_grid(grid)
    reach = 0.75 * epd  # overfills the pupil: the stop cuts the beam
    distances = x * np.linspace(*SWEEP)
    c = []
    for d in distances:
        origin, direction = axial_rays(z_ep, z_ep - d, u * reach, v * reach)
        (px, _, pz), (dx, _, dz), passed, _ = trace(rx, origin, direction)
        c.append(4.0 * float(np.std((px + (z_sensor - pz) / dz * dx)[passed])))
    c, w = np.asarray(c), 1.0 / distances
    fit = least_squares(lambda q: np.hypot(q[0] * (w - q[1]), q[2]) - c,
                        [float(c.max() / np.ptp(w)), 1.0 / x, float(c.min())])
    f_read = 1.0 / (1.0 / s_px + 1.0 / (para.pupil_magnification * x))
    return float(epd * s_px / abs(fit.x[0])), float(f_read / para.efl_mm)


def shipped():
    """The designs lensfit ships (``data_specs/lenses``): (name, prescription, f-number)."""
    from synth.lens.files import list_prescriptions, load_prescription
    from synth.lens.prescription import paraxial

    for name in list_prescriptions():
        rx = load_prescription(name)
        yield name, rx, float(rx.design_f_number or paraxial(rx).f_number)


def optiland_objectives():
    """optiland's all-spherical sample objectives, as :func:`rayoptics_objectives` gives
    rayoptics's: (name, prescription, f-number, where it came from, its half field of view in
    degrees: the largest field angle it is designed for)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import optiland.samples.objectives as objectives

        for name, cls in inspect.getmembers(objectives, inspect.isclass):
            if cls.__module__ != objectives.__name__:
                continue
            lens = cls()
            got = from_optiland(lens)
            if got is not None:
                yield name, got[0], got[1], f"optiland.samples.objectives.{name}", float(lens.fields.max_field)


def sample_objectives():
    """optiland's all-spherical sample objectives: (name, prescription, f-number)."""
    for name, rx, fno, *_ in optiland_objectives():
        yield name, rx, fno


def survey(stops=STOPS, designs=None) -> list[Row]:
    """The table: every design of ``designs`` (default: optiland's sample objectives, the
    shipped ones and rayoptics's) wide open and ``stops`` down."""
    from synth.lens.prescription import paraxial

    rows = []
    for source, found in designs or (("optiland.samples.objectives", sample_objectives()),
                                     ("data_specs/lenses", shipped()),
                                     *((s, [(n, rx, fno)]) for n, rx, fno, s, _ in rayoptics_objectives())):
        for name, rx, fno in found:
            para = paraxial(rx.with_f_number(fno))
            for k in stops:
                n = fno * 2.0 ** (k / 2.0)
                rows.append(Row(name, source, para.efl_mm, para.pupil_magnification, n, k, *design_ratios(rx, n)))
    return rows


def to_toml(rows: list[Row]) -> str:
    lines = ["# N_effective / (EFL/EPD) (ratio) and the focal length read at the real best focus / EFL (focal_ratio)",
             "# of published designs: written by `python -m lensfit.bench.designs --write` (lensfit/bench/designs.py",
             "# says how); lensfit.fitting.nominal carries their spreads into the f-number and the focal length.",
             f"x_over_f = {X_OVER_F:g}", ""]
    for r in rows:
        lines += ["[[design]]", f'name = "{r.design}"', f'source = "{r.source}"', f"efl_mm = {r.efl_mm:.4g}",
                  f"pupil_magnification = {r.pupil_magnification:.4g}", f"f_number = {r.f_number:.4g}",
                  f"stops_down = {r.stops_down}", f"ratio = {r.ratio:.5f}", f"focal_ratio = {r.focal_ratio:.5f}", ""]
    return "\n".join(lines)


def lens_file_text(rx, name: str, source: str, f_number: float) -> str:
    """A lens ``.toml`` (the format of ``data_specs/lenses``) holding ``rx``, monochromatic."""
    lines = [f"# {name}: written by lensfit.bench.designs.lens_file_text from {source}", f'name = "{name}"',
             f'source = "{source}"', f"design_f_number = {f_number:.6g}", "", "surface = ["]
    for s in rx.surfaces:
        radius = '"inf"' if math.isinf(s.radius_mm) else repr(float(s.radius_mm))
        stop = ", stop = true" if s.stop else ""
        lines.append(f"  {{ radius_mm = {radius}, thickness_mm = {float(s.thickness_mm)!r}, n = {float(s.n)!r}, "
                     f"semi_aperture_mm = {float(s.semi_aperture_mm)!r}{stop} }},")
    return "\n".join(lines + ["]", ""])


def survey_file() -> Path:
    """``data_specs/f_number_survey.toml`` (where the package's data_specs are)."""
    from lensfit.io.specs import specs_dir

    return specs_dir() / SURVEY_NAME


def read_survey(path: Path | None = None) -> list[Row]:
    import tomllib

    data = tomllib.loads((path or survey_file()).read_text())
    return [Row(d["name"], d["source"], d["efl_mm"], d["pupil_magnification"], d["f_number"], d["stops_down"],
                d["ratio"], d["focal_ratio"]) for d in data["design"]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lensfit.bench.designs", description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true", help=f"store the table in data_specs/{SURVEY_NAME}")
    args = ap.parse_args(argv)
    rows = survey()
    for r in rows:
        print(f"{r.design:26s} {r.source:28s} f {r.efl_mm:8.2f} mm  P {r.pupil_magnification:5.2f}  "
              f"f/{r.f_number:<5.2f} -{r.stops_down}  N_eff/N {r.ratio:.4f}  f_read/EFL {r.focal_ratio:.4f}")
    if args.write:
        survey_file().write_text(to_toml(rows))
        print(f"wrote {survey_file()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
