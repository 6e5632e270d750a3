"""Benchmark on real (thick, aberrated) lenses: stacks ray traced through every shipped
prescription (``data_specs/lenses``), fitted as a thin lens and as a thick lens.

Each lens gets the demo's calibration stack (``data_specs/scenes/demo.toml``: two ChArUco
boards at 0.5 to 3 times the focus distance, seven of twelve views tilted) with every length,
the pixel pitch included, scaled by f / 25 mm, so that field of view and blur in pixels are the
demo's at the same f-number (setting "far", focus X = 40 f), and the same stack at a sixth of
every distance and board size, two stops down (setting "near", focus X / 6 at twice the
f-number: the same pictures in pinhole terms with three times the blur): a focus bracket (unit
focusing) whose inverse focus distances differ by 1/(8 f). P rests on the two calibrations' focal
lengths in pixels: its relative sigma is about sqrt(2) sigma_cal P / (f |1/X_near - 1/X_far|),
2-3 % x P for this bracket with 0.2-0.4 % calibrations (a bracket at X and X / 3 gave 6-9 %).
1200 x 800 px (the demo's size; ``scale`` < 1 renders smaller), the lens focused at its best
focus (``focus_plane = "best"``). Three fits per lens:

- ``thin (one setting)``: the near setting alone, the pupil magnification P assumed 1 (what a
  thin-lens tool reports);
- ``thick, P given``: the near setting alone, P given as the prescription's (an assumption a
  user with the lens data can make);
- ``thick (bracket)``: both settings, P fitted.

Variants: ``bracket="narrow"`` puts the near setting at half the far one's distances (inverse
focus distances 1/(40 f) apart: P not determined, so carried); ``focusing="internal"`` renders
each design focused by moving one group (:func:`internally_focused_scene`), its stack saying
so, and the bracket fit is then each setting by itself, judged against each setting's own EFL;
``field="design"`` renders each of optiland's and rayoptics's designs at its own angle of view
where it is wider than the demo's (a retrofocus's 30 degrees, a wide angle's 35 at most), the
sensor, pixel pitch and boards widened by one factor, as a photographer would use the lens.

Errors are against the truth.json of each stack: the prescription's paraxial EFL, f-number =
EFL / entrance-pupil diameter, and the focus distance from the entrance pupil (the distance
imaged at best focus).
"""

from __future__ import annotations

import copy
import math
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from lensfit.bench.coverage import GAUSSIAN_HALF_WIDTH_RATIO, wilson_interval
from lensfit.errors import InputError, SpecError
from lensfit.fitting import fit
from lensfit.measurement.pipeline import measure_and_fit
from lensfit.io.specs import load_toml, specs_dir

LENGTH_KEYS = ("distance_mm", "square_mm", "marker_mm", "size_mm", "offset_mm", "pixel_pitch_mm", "focus_distance_mm")


def _scaled(value: Any, k: float) -> Any:
    if isinstance(value, list):
        return [_scaled(v, k) for v in value]
    return value * k if isinstance(value, (int, float)) and not isinstance(value, bool) else value


def _scale_lengths(node: Any, k: float) -> Any:
    if isinstance(node, dict):
        return {key: (_scaled(v, k) if key in LENGTH_KEYS else _scale_lengths(v, k)) for key, v in node.items()}
    if isinstance(node, list):
        return [_scale_lengths(v, k) for v in node]
    return node


#: The near setting's distances (and board sizes) as a fraction of the far setting's: a bracket
#: whose inverse focus distances differ by 5/X = 1/(8 f), for P to 2-3 % x P.
NEAR_FRACTION = 1.0 / 6.0
#: The near setting's f-number over the far one's: two stops down, so that its blur (six times
#: the far setting's at the same aperture) stays three times the far one's and its markers decode.
NEAR_STOP_FACTOR = 2.0
#: The near setting's distances for each bracket: "wide" (inverse focus distances 1/(8 f) apart,
#: P to a few per cent) and "narrow" (1/(40 f) apart: the near setting at half the far one's
#: distances, a bracket too narrow to fit P, which a photographer's two nearby settings are).
BRACKETS = {"wide": NEAR_FRACTION, "narrow": 0.5}


#: The widest half field of view (degrees, on the diagonal) ``lens_scene`` widens a design's stack
#: to: the boards grow with the sensor, and wider, their blur in px (which shrinks as the pixel
#: pitch grows) leaves little to fit.
FIELD_CAP_DEG = 35.0


def lens_scene(name: str, f_number: float = 11.0, spp: int = 64,
               wavelengths_nm: tuple[float, ...] = (), scale: float = 1.0, near_fraction: float = NEAR_FRACTION,
               focus_group: tuple[int, int] | None = None, field_deg: float | None = None) -> dict[str, Any]:
    """The demo scene scaled to the prescription ``name`` (setting "far": focus X = 40 f at
    ``f_number``) and the same scene at ``near_fraction`` (a sixth) of the distances with boards
    that much smaller (setting "near": focus ``near_fraction`` x X at ``NEAR_STOP_FACTOR`` x
    ``f_number``; the same pictures in pinhole terms, at a sixth three times the blur);
    ``scale`` x 1200 x 800 px; rendered grey from ``wavelengths_nm`` through the glasses'
    dispersion where given. Unit focusing, or with ``focus_group`` internal focusing by those
    surfaces (the sensor where the lens focuses infinity). With ``field_deg`` (the design's half
    field of view) wider than the demo's (9.8 degrees on the diagonal), the sensor, the pixel
    pitch, the boards and their offsets are widened by one factor to that field (at most
    ``FIELD_CAP_DEG``): the same pictures at the lens's own angle of view."""
    from synth.lens import load_prescription, paraxial

    efl = paraxial(load_prescription(name)).efl_mm
    demo = load_toml(specs_dir() / "scenes" / "demo.toml")
    k = efl / demo["lens"]["focal_length_mm"]
    scene = _scale_lengths(copy.deepcopy(demo), k)
    w, h = round(scale * demo["camera"]["width_px"]), round(scale * demo["camera"]["height_px"])
    scene["camera"].update(width_px=w, height_px=h, pixel_pitch_mm=demo["camera"]["pixel_pitch_mm"] * k
                           * demo["camera"]["width_px"] / w)
    focus = scene["lens"]["focus_distance_mm"]
    scene["lens"] = {"prescription": name, "f_number": f_number, "focus_distance_mm": focus}
    if focus_group is not None:
        scene["lens"].update(focusing="internal", focus_group=list(focus_group))
    if wavelengths_nm:
        scene["lens"]["wavelengths_nm"] = [float(w) for w in wavelengths_nm]
    scene["render"] = {"effects": ["defocus"], "method": "raytrace", "samples_per_pixel": spp, "seed": 0}
    if field_deg is not None:
        demo_half = math.atan(math.hypot(w, h) * scene["camera"]["pixel_pitch_mm"] / 2 / efl)
        q = math.tan(max(demo_half, math.radians(min(field_deg, FIELD_CAP_DEG)))) / math.tan(demo_half)
        scene["camera"]["pixel_pitch_mm"] *= q
        for obj in scene["object"]:
            obj.update(square_mm=obj["square_mm"] * q, marker_mm=obj["marker_mm"] * q,
                       size_mm=[v * q for v in obj["size_mm"]])
        for shot in scene["shot"]:
            for pose in shot.get("pose", []):
                pose["offset_mm"] = [v * q for v in pose.get("offset_mm", [0.0, 0.0])]
    near = _scale_lengths({"object": scene["object"], "shot": scene["shot"]}, near_fraction)
    for obj in near["object"]:
        obj["id"] = f"{obj['id']}-near"
    for shot in near["shot"]:
        shot["objects"] = [f"{o}-near" for o in shot["objects"]]
        shot["pose"] = [{**p, "id": f"{p['id']}-near"} for p in shot.get("pose", [])]
    scene["object"] = scene["object"] + near["object"]
    scene["shot"] = ([{**s, "setting": "near", "focus_distance_mm": near_fraction * focus,
                       "f_number": NEAR_STOP_FACTOR * f_number, "name": f"near_{i:03d}"}
                      for i, s in enumerate(near["shot"])]
                     + [{**s, "setting": "far", "name": f"far_{i:03d}"} for i, s in enumerate(scene["shot"])])
    scene["name"] = f"{name}-bracket"
    return scene


def _errors(result, truth: dict[str, Any], label: str) -> dict[str, Any]:
    t = truth["settings"][label]
    out = {}
    f_true = t.get("focal_length_mm", truth["focal_length_mm"])  # the setting's own where the lens breathes
    pairs = [("focal_length_mm", "focal_length_mm", f_true), ("f_number", "f_number", t["f_number"]),
             ("focus_distance_mm", "focus_distance_mm", t["focus_distance_mm"])]
    if "real_ray_f_number" in t:  # what blur follows: the real entrance pupil (pupil aberration)
        pairs.append(("f_number_real_ray", "f_number_effective", t["real_ray_f_number"]))
    for key, q, tv in pairs:
        # the blur's own f-number where the fit reports the nominal one beside it (a lens not
        # declared ideal), else the one it reports
        e = result.settings[label].get(q) or result.settings[label]["f_number"]
        out[key] = _judged(e, tv)
    return out


def _judged(e, truth: float) -> dict[str, Any]:
    """An estimate against its truth: the relative error, whether its 95 % interval holds the
    truth, and the interval's half-width relative to the truth (None where a bound is open)."""
    bounded = e.ci95 is not None and e.ci95[0] is not None and e.ci95[1] is not None
    return {"estimate": e.value, "truth": truth, "relative_error": None if e.value is None else e.value / truth - 1,
            "within_ci95": None if e.ci95 is None else bool(
                (e.ci95[0] is None or e.ci95[0] <= truth) and (e.ci95[1] is None or truth <= e.ci95[1])),
            "half_width_relative": (e.ci95[1] - e.ci95[0]) / 2 / truth if bounded and e.value is not None else None}


def spectral_designs() -> list[str]:
    """The shipped designs whose glasses have a dispersion (the ones a spectral render accepts)."""
    from synth.lens import list_prescriptions, load_prescription

    return [n for n in list_prescriptions() if not load_prescription(n).undispersed_surfaces()]


def run(names: list[str] | None = None, spp: int = 64, f_number: float | None = 11.0,
        progress: Callable[[str], None] | None = None, wavelengths_nm: tuple[float, ...] = (),
        scale: float = 1.0, keep: Path | None = None, reuse: Path | None = None,
        designs: str = "shipped", bracket: str = "wide", focusing: str = "unit",
        field: str = "demo") -> dict[str, Any]:
    """Render, measure and fit every lens (with ``wavelengths_nm``: every lens with dispersion,
    rendered grey through those wavelengths); returns rows of errors and seconds. With ``keep``
    each stack is written to ``keep / NAME`` and left there (an existing stack is an error, never
    replaced); otherwise to a temporary folder that is removed. With ``reuse`` nothing is rendered:
    the stacks a run with ``keep`` wrote there are measured and fitted again (the rendering
    arguments are then theirs, not these). ``designs``: "shipped" (``data_specs/lenses``),
    "optiland" (optiland's all-spherical sample objectives, which lensfit does not ship, written
    as lens files beside the stacks) or "rayoptics" (the photographic objectives among rayoptics's
    sample lens files, likewise); ``f_number`` None: each design wide open (its own f-number,
    the near setting two stops down). ``bracket``: "wide" or "narrow" (``BRACKETS``);
    ``focusing``: "unit" (the whole lens moves) or "internal" (the lens's rear group, else its
    front group, moves: :func:`internally_focused_scene`; the bracket then fitted as declared,
    each setting by itself); ``field``: "demo" (every design at the demo's angle of view) or
    "design" (optiland's and rayoptics's designs each at its own, where wider: ``lens_scene``'s
    ``field_deg``)."""
    import json

    from synth.lens import list_prescriptions
    from synth.rendering import render
    from synth.scene import scene_from_dict
    from synth.stack import write_stack

    unshipped: dict[str, tuple[Any, float, str]] = {}  # name: (prescription, f-number, source) not shipped
    lens_files: dict[str, tuple[Path, float]] = {}  # name: (its lens file, f-number) where not shipped
    fields: dict[str, float] = {}  # name: the design's half field of view (degrees) where known
    if designs in ("optiland", "rayoptics"):
        from lensfit.bench.designs import optiland_objectives, rayoptics_objectives

        found = list(optiland_objectives() if designs == "optiland" else rayoptics_objectives())
        unshipped = {f"{designs}-{n}": (rx, fno, src) for n, rx, fno, src, _ in found}
        fields = {f"{designs}-{n}": v for n, *_, v in found if v is not None}
    if field not in ("demo", "design"):
        raise InputError("field", field, "demo or design")
    if field == "design" and designs == "shipped":
        raise InputError("field", field, "demo with the shipped designs, whose lens files state no angle of view",
                         "add --designs optiland or --designs rayoptics, which state theirs")
    if designs != "shipped":
        names = [n for n in (names or list(unshipped)) if n in unshipped]
    else:
        names = names or (spectral_designs() if wavelengths_nm else list_prescriptions())
    if keep is not None:
        taken = [n for n in names if (Path(keep) / n).exists()]
        if taken:
            raise InputError("keep", str(keep), f"a folder without stacks named {', '.join(taken)}",
                             "name a new folder; existing stacks are never replaced")
    if reuse is not None:
        absent = [n for n in names if not (Path(reuse) / n / "truth.json").is_file()]
        if absent:
            raise InputError("reuse", str(reuse), f"a folder holding the stacks {', '.join(absent)}, written there by "
                             "an earlier run with keep", "render them there first")
    say = progress or (lambda msg: None)
    rows = []
    with tempfile.TemporaryDirectory(prefix="lensfit-bench-lenses-") as tmp:
        root = Path(tmp) if keep is None else Path(keep)
        if unshipped and reuse is None:
            lens_files = _write_lens_files(root / "lenses", {n: unshipped[n] for n in names})
        for name in names:
            if reuse is not None:
                folder, t_render = Path(reuse) / name, None
            else:
                say(f"{name}: rendering 24 shots")
                t0 = time.perf_counter()
                path, design_n = lens_files.get(name, (None, None))
                lens = name if path is None else str(path)
                n_far = f_number if f_number is not None else _wide_open(lens, design_n)
                try:
                    args = dict(f_number=n_far, spp=spp, wavelengths_nm=wavelengths_nm, scale=scale,
                                near_fraction=BRACKETS[bracket],
                                field_deg=fields.get(name) if field == "design" else None)
                    scene = (scene_from_dict(lens_scene(lens, **args), f"<{name} bracket>") if focusing == "unit"
                             else internally_focused_scene(lens, f"<{name} bracket>", **args))
                    folder = write_stack(render(scene), root / name)
                except (InputError, SpecError) as exc:  # a design this bench cannot render so: a row saying why
                    rows.append({"lens": name, "refused": f"not rendered: {exc}", "fits": {}})
                    continue
                t_render = time.perf_counter() - t0
            truth = json.loads((folder / "truth.json").read_text())
            say(f"{name}: measuring")
            t0 = time.perf_counter()
            # As `lensfit fit`: the images tested for the Airy pattern, which decides the readings
            # (the spots' shapes, or the pattern modelled; lensfit.fitting.refits); its fit is the bracket's.
            try:
                table, bracket_fit, _ = measure_and_fit(folder, auto_diffraction=True)
            except (InputError, SpecError) as exc:  # the stack refused as a user's would be: a row saying why
                rows.append({"lens": name, "refused": str(exc), "fits": {}})
                continue
            t_measure = time.perf_counter() - t0
            P = truth["settings"]["near"]["pupil_magnification"]
            internal = truth["settings"]["near"].get("lens", {}).get("focusing") == "internal"
            fits = {}
            if "near" not in table.left_out_settings:  # (else the bracket's refuses it, naming why)
                one = copy.copy(table)
                one.samples = [s for s in table.samples if s.setting == "near"]
                one.intrinsics = {"near": table.intrinsics["near"]}
                fits = {"default (one setting)": fit(one), "thin (one setting)": fit(one, pupil_magnification=1.0),
                        "thick, P given (one setting)": fit(one, pupil_magnification=P)}
            fits[BRACKET_FITS[internal]] = bracket_fit
            calibration = {label: {"focal_length_px": k.focal_length_px, "sigma": k.focal_length_sigma_px,
                                   "sigma_method": k.focal_length_sigma_method, "views": k.views,
                                   "relative_error": k.focal_length_px / truth["settings"][label]["focal_length_px"] - 1}
                           for label, k in table.intrinsics.items()}
            row = {"lens": name, "pupil_magnification": P, "f_number_far": truth["settings"]["far"]["f_number"],
                   "field_deg": fields.get(name), "sensor_diagonal_mm": math.hypot(truth["width_px"],
                                                                                   truth["height_px"])
                   * truth["pixel_pitch_mm"],
                   "focus_group": truth["settings"]["near"].get("lens", {}).get("focus_group"),
                   "focal_length_mm": {label: t.get("focal_length_mm") for label, t in truth["settings"].items()},
                   "f_number_near": truth["settings"]["near"]["f_number"],
                   "seconds_render": t_render, "seconds_measure": t_measure,
                   "calibration": calibration, "fits": {}}
            for how, res in fits.items():
                errors = _errors(res, truth, "near")
                # P judged where estimated, not given; the bracket's only where it fitted P (one
                # setting left out, its prior's open interval would count as held)
                if (res.pupil_magnification.value is not None and (res.pupil_magnification.sigma or 0) > 0
                        and (how not in BRACKET_FITS.values() or res.pupil_magnification_source == "fitted")):
                    errors["pupil_magnification"] = _judged(res.pupil_magnification, P)
                row["fits"][how] = {"errors": errors, "result": res.code,
                                    "errors_far": _errors(res, truth, "far") if "far" in res.settings else None,
                                    "pupil_magnification": res.pupil_magnification.value,
                                    "pupil_magnification_sigma": res.pupil_magnification.sigma,
                                    "field_curvature_per_m": {
                                        label: {"value": e.value, "sigma": e.sigma, "reason": e.reason}
                                        for label, qs in res.settings.items()
                                        if (e := qs.get("field_curvature_per_m")) is not None}}
            rows.append(row)
    return {"rows": rows, "samples_per_pixel": spp, "f_number": f_number, "bracket": bracket, "focusing": focusing,
            "field": field,
            "inverse_focus_distance_gap_per_focal_length": 1.0 / (40.0 * BRACKETS[bracket]) - 1.0 / 40.0,
            "near_f_number": None if f_number is None else NEAR_STOP_FACTOR * f_number, "designs": designs,
            "scale": scale, "wavelengths_nm": list(wavelengths_nm), "reused": None if reuse is None else str(reuse),
            "coverage": coverage(rows)}


#: The bracket's fit as ``measure_and_fit`` makes it, by how the stack says the lens focuses:
#: unit (f and P shared, P fitted) or internal (each setting by itself).
BRACKET_FITS = {False: "thick (bracket, P fitted)", True: "bracket, focusing internal (per setting)"}


def internally_focused_scene(lens: str, where: str, **scene_args):
    """:func:`lens_scene` (with ``scene_args``) resolved by synth with ``lens`` focusing
    internally: everything behind the stop moving (rear focusing, the common modern choice)
    where synth can focus both settings so, else everything in front of it (front-cell
    focusing). Raises InputError, with synth's reasons, where neither group does."""
    from synth.lens import check_focus_group, load_prescription
    from synth.scene import scene_from_dict

    rx = load_prescription(lens)
    k, why = rx.stop_index, []
    for group in ((k + 1, len(rx.surfaces) - 1), (0, k - 1)):
        if check_focus_group(rx, group) is not None:
            continue
        try:
            return scene_from_dict(lens_scene(lens, focus_group=group, **scene_args), where)
        except SpecError as exc:
            why.append(str(exc))
    raise InputError("focusing", "internal", f"a group of {rx.name} that focuses both settings",
                     "; ".join(why) or "it has no air-bounded group on either side of its stop")


def _write_lens_files(folder: Path, designs: dict[str, tuple[Any, float, str]]) -> dict[str, tuple[Path, float]]:
    """``designs`` (name: prescription, f-number and where it came from) as lens files in ``folder``."""
    from lensfit.bench.designs import lens_file_text

    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, (rx, fno, source) in designs.items():
        path = folder / f"{name}.toml"
        path.write_text(lens_file_text(rx, name, source, fno))
        out[name] = (path, fno)
    return out


def _wide_open(lens: str, design_n: float | None) -> float:
    """The design's own f-number, or where its clear apertures cut the axial beam at the far
    setting's focus (40 focal lengths; synth refuses such a scene) the fastest it opens to there,
    rounded up to a tenth of a stop."""
    from synth.lens import load_prescription, paraxial
    from synth.lens.focus import fastest_f_number

    rx = load_prescription(lens)
    para = paraxial(rx)
    n = float(design_n or rx.design_f_number or para.f_number)
    fastest = fastest_f_number(rx, para.entrance_pupil_z_mm - 40.0 * para.efl_mm)
    return n if fastest <= n else round(fastest * 2 ** 0.05, 2)


#: The quantities whose 95 % intervals the coverage counts, each against its truth.
COVERED = ("focal_length_mm", "f_number", "f_number_real_ray", "focus_distance_mm", "pupil_magnification")


def coverage(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per fit and quantity over the lenses (both settings where the fit has both): how many
    95 % intervals held the truth of how many reported, the refusals, and the Wilson 95 %
    interval of the rate; and the mean absolute relative error beside the mean relative 95 %
    half-width of the bounded intervals, whose ratio is the suites' ``half_width95_over_mean_error``
    (``lensfit.bench.coverage.interval_honesty``: ``GAUSSIAN_HALF_WIDTH_RATIO`` where right)."""
    out: dict[str, dict[str, Any]] = {}
    errors_of: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for row in rows:
        for how, fr in row["fits"].items():
            per = out.setdefault(how, {q: {"held": 0, "reported": 0, "refused": 0} for q in COVERED})
            for errors in (fr["errors"], fr.get("errors_far")):
                for q in COVERED:
                    e = (errors or {}).get(q)
                    if e is None:
                        continue
                    if e["relative_error"] is None:
                        per[q]["refused"] += 1
                    else:
                        per[q]["reported"] += 1
                        per[q]["held"] += bool(e["within_ci95"])
                        if e.get("half_width_relative") is not None:
                            errors_of.setdefault((how, q), []).append((abs(e["relative_error"]),
                                                                       e["half_width_relative"]))
    for how, per in out.items():
        for q, c in per.items():
            c["rate"] = c["held"] / c["reported"] if c["reported"] else None
            c["wilson95"] = wilson_interval(c["held"], c["reported"]) if c["reported"] else None
            pairs = errors_of.get((how, q), [])
            c["mean_abs_error"] = sum(a for a, _ in pairs) / len(pairs) if pairs else None
            c["mean_half_width"] = sum(h for _, h in pairs) / len(pairs) if pairs else None
    return out


#: The image scale the suite's records are rendered at (``--scale``); a record at another scale
#: is a variant of its own.
RECORD_SCALE = 0.5


def record_name(bracket: str = "wide", focusing: str = "unit", designs: str = "optiland",
                f_number: float | None = None, field: str = "demo", scale: float = RECORD_SCALE) -> str:
    """The record's name (its file DIR/NAME.json): one current record per variant of the suite
    (optiland's designs wide open at ``RECORD_SCALE``: ``lenses``; the shipped or rayoptics's
    designs, a given f-number, a narrow bracket, internal focusing, the designs' own field and
    another scale each add to it, e.g. ``lenses_f5.6_narrow``, ``lenses_rayoptics``,
    ``lenses_scale1``)."""
    return ("lenses" + {"shipped": "_shipped", "rayoptics": "_rayoptics"}.get(designs, "")
            + ("" if f_number is None else f"_f{f_number:g}") + ("_narrow" if bracket == "narrow" else "")
            + ("_internal" if focusing == "internal" else "") + ("_design_field" if field == "design" else "")
            + ("" if scale == RECORD_SCALE else f"_scale{scale:g}"))


#: How the record's tables name the quantities.
QUANTITY_NAMES = {"focal_length_mm": "f", "f_number": "N (nominal)", "f_number_real_ray": "N (real rays)",
                  "focus_distance_mm": "focus distance", "pupil_magnification": "P"}


def markdown(doc: dict[str, Any]) -> str:
    """The record as the validation page's section: coverage per fit and quantity, then each
    design's errors."""
    what = ("each wide open (far), two stops down (near)" if doc.get("f_number") is None else
            f"far f/{doc['f_number']:g}, near f/{doc['near_f_number']:g}")
    variant = "".join([", wide open" if doc.get("f_number") is None else f", f/{doc['f_number']:g}",
                       ", narrow bracket" if doc.get("bracket") == "narrow" else "",
                       ", internal focusing" if doc.get("focusing") == "internal" else "",
                       ", each at its own field of view" if doc.get("field") == "design" else "",
                       f", scale {doc['scale']:g}" if doc.get("scale", RECORD_SCALE) != RECORD_SCALE else ""])
    out = [f"### Real lenses (`lensfit bench-lenses`, {doc.get('designs', 'shipped')} designs{variant})", "",
           f"`{doc.get('command', 'lensfit bench-lenses')}`, {doc.get('date', '')}, {doc.get('cores', '?')} cores. "
           f"The demo stack scaled to each design and ray traced through it ({what}, {doc['samples_per_pixel']} "
           "spp, scale " f"{doc['scale']:g}); fitted as a user would (default: one setting, P and the nominal f-number "
           "carried by their priors) and as the two-setting bracket ("
           + ("each setting by itself, as the stack declares the rear or front group to move"
              if doc.get("focusing") == "internal" else "P fitted")
           + f"; inverse focus distances {doc.get('inverse_focus_distance_gap_per_focal_length', 0.125):.3g} / f apart). "
           "The 95 % intervals holding the truth "
           "(Wilson's 95 % interval of the rate), and the mean absolute error beside the mean 95 % half-width, both "
           "relative to the truth.", "",
           "| fit | quantity | intervals holding the truth | refused | mean error | mean 95 % half-width | "
           f"half-width / mean error ({GAUSSIAN_HALF_WIDTH_RATIO:.2f} if right) |", "|---|---|---|---|---|---|---|"]
    for how, per in doc["coverage"].items():
        for q, c in per.items():
            if not c["reported"] and not c["refused"]:
                continue
            held = (f"{c['held']} of {c['reported']} ({100 * c['wilson95'][0]:.0f}-{100 * c['wilson95'][1]:.0f} %)"
                    if c["reported"] else "")
            err = "" if c.get("mean_abs_error") is None else f"{100 * c['mean_abs_error']:.2f} %"
            half = "" if c.get("mean_half_width") is None else f"{100 * c['mean_half_width']:.2f} %"
            ratio = (f"{c['mean_half_width'] / c['mean_abs_error']:.2f}" if c.get("mean_half_width") is not None
                     and c.get("mean_abs_error") else "")
            out.append(f"| {how} | {QUANTITY_NAMES.get(q, q)} | {held} | {c['refused']} | {err} | {half} | {ratio} |")

    def cell(e):
        if e is None:
            return ""
        if e["relative_error"] is None:
            return "refused"
        return f"{100 * e['relative_error']:+.2f} %" + ("" if e["within_ci95"] else " (outside)")

    out += ["", "| design | fit | f | N (nominal) | N (real rays) | focus distance | P |",
            "|---|---|---|---|---|---|---|"]
    for row in doc["rows"]:
        if row.get("refused"):
            out.append(f"| {row['lens']} | refused: {row['refused'][:160]} | | | | | |")
            continue
        for how in ("default (one setting)", *BRACKET_FITS.values()):
            fr = row["fits"].get(how)
            if fr is None:
                continue
            for label, e in (("near", fr["errors"]), ("far", fr.get("errors_far"))):
                if e is None:
                    continue
                p = cell(fr["errors"].get("pupil_magnification")) if label == "near" else ""
                out.append(f"| {row['lens']} | {how}, {label} | {cell(e['focal_length_mm'])} | {cell(e['f_number'])} | "
                           f"{cell(e.get('f_number_real_ray'))} | {cell(e['focus_distance_mm'])} | {p} |")
    return "\n".join(out)
