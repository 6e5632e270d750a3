"""Scene specs: read, validate, and resolve into shots ready to render.

A scene file (TOML) is validated against ``data_specs/schemas/scene.schema.json``; then the
checks a schema cannot express (focus beyond the focal length, targets in front of the lens,
consistent shots, target-specific fields) run here. Every problem is a
:class:`lensfit.errors.SpecError` naming the file, the field and the bad value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.errors import InputError, SpecError
from lensfit.io.specs import load_toml, validate
from synth.effects import Effects, parse as parse_effects
from synth.geometry import CompoundLensCamera, Pose, ThinLensCamera

DEFAULTS = {
    "effects": ("defocus",),
    "method": "auto",
    "samples_per_pixel": 64,
    "supersampling": 4,
    "seed": 0,
    "format": "png",
    "jpeg_quality": 95,
    "mitsuba_variant": "scalar_rgb",
    "background": 0.2,
}


@dataclass(frozen=True)
class TargetSpec:
    """A planar object's appearance: what it shows, independent of where it is.

    ``params`` holds the target-specific fields with defaults filled in (squares, square_mm,
    marker_mm, dictionary, angle_deg, edge_mm, spokes, file, value, dark, light).
    """

    id: str
    target: str
    size_mm: tuple[float, float]
    params: dict[str, Any] = field(hash=False, compare=False)


@dataclass(frozen=True)
class PlacedObject:
    target: TargetSpec
    pose: Pose


@dataclass(frozen=True)
class Shot:
    """One image of the stack: a lens setting and the objects at their poses."""

    name: str
    setting: str
    camera: ThinLensCamera
    objects: tuple[PlacedObject, ...]
    shutter_s: float | None = None  # exposure overrides (the exposure effect)
    iso: float | None = None


@dataclass(frozen=True)
class RenderSettings:
    effects: tuple[str, ...]
    method: str
    samples_per_pixel: int
    supersampling: int
    seed: int
    format: str
    jpeg_quality: int = 95
    mitsuba_variant: str = "scalar_rgb"


@dataclass(frozen=True)
class Scene:
    """A validated scene: shared camera and lens, targets, render settings and shots."""

    path: str
    name: str
    pixel_pitch_mm: float
    width_px: int
    height_px: int
    focal_length_mm: float
    aperture: dict[str, Any] = field(hash=False, compare=False)
    render: RenderSettings = None  # type: ignore[assignment]
    background_value: float = 0.2
    targets: tuple[TargetSpec, ...] = ()
    shots: tuple[Shot, ...] = ()
    effects: Effects = Effects()

    def with_render(self, **changes) -> "Scene":
        """A copy with render settings replaced (e.g. method, samples_per_pixel, seed)."""
        return replace(self, render=replace(self.render, **{k: v for k, v in changes.items() if v is not None}))


def _distance(value) -> float:
    return math.inf if value == "inf" else float(value)


def _pitch(camera: dict, path) -> float:
    from lensfit.io.sensors import sensor_format

    sources = [k for k in ("pixel_pitch_mm", "sensor", "sensor_width_mm") if k in camera]
    if not sources:
        raise SpecError(path, "camera", "needs pixel_pitch_mm, sensor (a format name) or sensor_width_mm")
    if len(sources) > 1:
        raise SpecError(path, f"camera.{sources[1]}",
                        f"conflicts with camera.{sources[0]}; give only one way to set the pixel pitch")
    if "pixel_pitch_mm" in camera:
        return float(camera["pixel_pitch_mm"])
    if "sensor_width_mm" in camera:
        return float(camera["sensor_width_mm"]) / camera["width_px"]
    try:
        fmt = sensor_format(camera["sensor"])
    except InputError as exc:
        raise SpecError(path, "camera.sensor", f"got {camera['sensor']!r}: unknown format; {exc.hint}") from None
    return fmt.width_mm / camera["width_px"]


def _target(i: int, obj: dict, path, focal_length_mm: float) -> TargetSpec:
    where = f"object[{i}]"
    kind = obj["target"]
    p: dict[str, Any] = {}

    def need(name):
        if name not in obj:
            raise SpecError(path, f"{where}.{name}", f"is required for target = {kind!r}")
        return obj[name]

    size = obj.get("size_mm")
    if kind in ("charuco", "checkerboard"):
        squares = tuple(need("squares"))
        square = float(need("square_mm"))
        p.update(squares=squares, square_mm=square, dark=obj.get("dark", 0.05), light=obj.get("light", 0.95))
        pattern = (squares[0] * square, squares[1] * square)
        if kind == "charuco":
            marker = float(need("marker_mm"))
            if marker >= square:
                raise SpecError(path, f"{where}.marker_mm", f"got {marker:g}: must be < square_mm ({square:g})")
            p.update(marker_mm=marker, dictionary=obj.get("dictionary", "DICT_5X5_100"),
                     legacy_pattern=bool(obj.get("legacy_pattern", False)))
            import cv2

            if not hasattr(cv2.aruco, p["dictionary"]):
                raise SpecError(path, f"{where}.dictionary", f"got {p['dictionary']!r}: not an OpenCV ArUco dictionary")
            n_markers = (squares[0] * squares[1]) // 2
            capacity = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, p["dictionary"])).bytesList.shape[0]
            if n_markers > capacity:
                raise SpecError(path, f"{where}.squares", f"got {list(squares)}: needs {n_markers} markers, "
                                f"{p['dictionary']} has {capacity}; use a larger dictionary")
        if size is None:
            size = pattern
        elif size[0] < pattern[0] - 1e-9 or size[1] < pattern[1] - 1e-9:
            raise SpecError(path, f"{where}.size_mm", f"got {list(size)}: smaller than the pattern "
                            f"{pattern[0]:g} x {pattern[1]:g} mm (squares x square_mm)")
    elif kind == "slanted-edge":
        size = need("size_mm")
        p.update(angle_deg=float(obj.get("angle_deg", 5.0)),
                 edge_mm=float(obj.get("edge_mm", 0.5 * min(size))),
                 dark=obj.get("dark", 0.05), light=obj.get("light", 0.95))
        if p["edge_mm"] * (abs(math.cos(math.radians(p["angle_deg"]))) + abs(math.sin(math.radians(p["angle_deg"])))) > min(size):
            raise SpecError(path, f"{where}.edge_mm", f"got {p['edge_mm']:g}: the rotated square does not fit in size_mm")
    elif kind == "siemens-star":
        size = need("size_mm")
        p.update(spokes=int(obj.get("spokes", 36)), dark=obj.get("dark", 0.05), light=obj.get("light", 0.95))
    elif kind == "image":
        size = need("size_mm")
        file = Path(need("file"))
        if not file.is_absolute():
            file = Path(path).parent / file
        if not file.is_file():
            raise SpecError(path, f"{where}.file", f"got {obj['file']!r}: no such file (relative to the scene file)")
        # dark/light: reflectance of the file's black and white (a print's ink and paper); the
        # file's values as they are unless given
        p.update(file=str(file), encoding=obj.get("encoding", "srgb"), dark=float(obj.get("dark", 0.0)),
                 light=float(obj.get("light", 1.0)))
    elif kind == "uniform":
        size = need("size_mm")
        p.update(value=float(obj.get("value", 0.5)))
    return TargetSpec(id=obj.get("id", f"{kind}-{i}"), target=kind, size_mm=(float(size[0]), float(size[1])), params=p)


def _check_in_front(path, where: str, target: TargetSpec, pose: Pose, focal_length_mm: float) -> None:
    w, h = target.size_mm
    corners = pose.to_camera(np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]]))
    z = corners[:, 2].min()
    if z <= focal_length_mm:
        raise SpecError(path, where, f"a corner of {target.id!r} is at depth {z:.4g} mm, not beyond the focal "
                        f"length ({focal_length_mm:g} mm); move it further away or reduce its tilt")


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file; resolve its shots.

    Raises
    ------
    lensfit.errors.SpecError
        Naming the file, the field and the bad value.
    """
    path = Path(path)
    data = load_toml(path)
    return scene_from_dict(data, path)


#: Effects a compound lens produces by itself (tracing), which a scene may not add on top.
_TRACED_EFFECTS = ("distortion", "chromatic_aberration", "vignetting")


def _prescription(lens: dict, path):
    """The compound lens a scene's [lens] names, or None for a thin lens."""
    from synth.lens import load_prescription, prescription_from_dict

    if "surface" in lens:  # an inline surface table
        if "prescription" in lens or "focal_length_mm" in lens:
            raise SpecError(path, "lens.surface", "conflicts with lens." + ("prescription" if "prescription" in lens
                            else "focal_length_mm") + " (the surface table is the lens); remove one")
        try:
            return prescription_from_dict({"name": "inline", "surface": lens["surface"]}, path)
        except SpecError as exc:
            raise SpecError(path, "lens", str(exc)) from None
    if "prescription" not in lens:
        if "focal_length_mm" not in lens:
            raise SpecError(path, "lens.focal_length_mm", "is required but missing (or give lens.prescription, a "
                            "compound lens)")
        return None
    if "focal_length_mm" in lens:
        raise SpecError(path, "lens.focal_length_mm", "conflicts with lens.prescription, whose EFL is the focal "
                        "length; remove one")

    name = lens["prescription"]
    if name.endswith(".toml") and not Path(name).is_absolute():
        name = str(Path(str(path)).parent / name)
    try:
        return load_prescription(name)
    except SpecError as exc:
        raise SpecError(path, "lens.prescription", str(exc)) from None


def _wavelengths(lens: dict, path, rx, effects) -> tuple[float, ...]:
    """The spectral samples of ``[lens] wavelengths_nm`` (``synth.spectral``), checked."""
    from synth import spectral

    if "wavelengths_nm" not in lens:
        if lens.get("colour"):
            raise SpecError(path, "lens.colour", "asks for colour from spectral samples: give lens.wavelengths_nm "
                            "too (e.g. [465, 550, 610])")
        return ()  # colour channels (a mosaic, say) then all see the lens at the d line
    waves = tuple(float(w) for w in lens["wavelengths_nm"])
    lo, hi = spectral.WAVELENGTH_RANGE_NM
    for i, w in enumerate(waves):
        if not lo <= w <= hi:
            raise SpecError(path, f"lens.wavelengths_nm[{i}]",
                            f"got {w:g}: a visible wavelength from {lo:g} to {hi:g} nm")
    if len(set(waves)) != len(waves):
        raise SpecError(path, "lens.wavelengths_nm", f"got {list(waves)}: each wavelength once")
    missing = rx.undispersed_surfaces()
    if missing:
        raise SpecError(path, "lens.wavelengths_nm", f"{rx.name}'s surface[{missing[0]}] (n = "
                        f"{rx.surfaces[missing[0]].n:g}) has no V or glass, so its index at other wavelengths is "
                        "unknown; give the lens's glasses, or remove wavelengths_nm")
    if effects.channels == 3:
        gap = spectral.uncovered_channel(waves)
        if gap is not None:
            raise SpecError(path, "lens.wavelengths_nm", f"got {list(waves)}: no wavelength for the {gap} channel "
                            f"of a colour image; add one within {2 * spectral.CHANNEL_SIGMA_NM:g} nm of it")
    return waves


def _internal_focusing(lens: dict, path, rx, wavelengths: tuple[float, ...]):
    """For ``[lens] focusing = "internal"``: a function of a setting's f-number and focus
    distance (and the field to name) giving its lens, the group moved to focus that distance on
    the fixed sensor, and the group's shift (mm, + towards the image); None for unit focusing."""
    from synth.lens import check_focus_group, internal_focus, polychromatic_best_focus_image_z, image_z

    how = lens.get("focusing", "unit")
    if how == "unit":
        if "focus_group" in lens:
            raise SpecError(path, "lens.focus_group", "moves a group only with focusing = \"internal\"; add that or "
                            "remove focus_group")
        return None
    if "focus_group" not in lens:
        raise SpecError(path, "lens.focus_group", "is required with focusing = \"internal\": the first and last "
                        "surface index of the group that moves, e.g. [6, 10]")
    group = (int(lens["focus_group"][0]), int(lens["focus_group"][1]))
    problem = check_focus_group(rx, group)
    if problem is not None:
        raise SpecError(path, "lens.focus_group", f"got {list(group)}: must be {problem}")
    design = rx.with_f_number(float(lens["f_number"]))
    if lens.get("focus_plane", "best") == "best":
        rxs = [design.at_wavelength(w) for w in wavelengths] if wavelengths else [design]
        sensor_z = polychromatic_best_focus_image_z(rxs, -math.inf)
    else:
        sensor_z = image_z(design, -math.inf)
    made: dict[tuple[float, float], tuple[Any, float]] = {}

    def focused(N: float, D: float, where: str):
        if (N, D) not in made:
            try:
                made[(N, D)] = internal_focus(rx.with_f_number(N), group, D, sensor_z, wavelengths,
                                              lens.get("focus_plane", "best"))
            except ValueError as exc:
                raise SpecError(path, where, f"got {D:g}: {rx.name} does not focus there internally ({exc}); "
                                "choose a farther focus distance or another lens.focus_group") from None
        return made[(N, D)]

    return focused


#: Share of the axial beam that clear apertures other than the stop may block before an
#: f-number counts as faster than the lens opens.
AXIAL_CLIPPING_LIMIT = 0.02


def _check_opens(path, where: str, rx, N: float, D: float) -> None:
    """Refuse an f-number the compound lens cannot open to: where other clear apertures than the
    stop cut the axial beam, the stop no longer sets the f-number and the blur is not the lens's."""
    from synth.lens import axial_beam_clipped, fastest_f_number, paraxial

    stopped = rx.with_f_number(N)
    z_obj = paraxial(stopped).entrance_pupil_z_mm - D
    clipped = axial_beam_clipped(stopped, z_obj)
    if clipped > AXIAL_CLIPPING_LIMIT:
        fastest = fastest_f_number(rx, z_obj, AXIAL_CLIPPING_LIMIT)
        if not math.isfinite(fastest):
            raise SpecError(path, where, f"got {N:g}: the clear apertures of {rx.name} block the axial beam at "
                            "every f-number; check its semi_aperture_mm values")
        raise SpecError(path, where, f"got {N:g}: {rx.name} does not open that far (its clear apertures block "
                        f"{100 * clipped:.0f} % of the axial beam at this focus); use f/{math.ceil(fastest * 10) / 10:g} "
                        "or slower")


def scene_from_dict(data: dict[str, Any], path: str | Path = "<scene>") -> Scene:
    """Validate a scene given as a dict (as parsed from TOML) and resolve its shots."""
    validate(data, "scene", path)
    cam, lens = data["camera"], data["lens"]
    pitch = _pitch(cam, path)
    rx = _prescription(lens, path)
    if rx is not None:
        from synth.lens import paraxial

        f = paraxial(rx).efl_mm
    else:
        f = float(lens["focal_length_mm"])
    aperture = lens.get("aperture", "circle")
    aperture = {"shape": aperture} if isinstance(aperture, str) else dict(aperture)
    render = data.get("render", {})
    names = tuple(render.get("effects", DEFAULTS["effects"]))
    effects = parse_effects(data, path, names, aperture)
    if rx is not None:
        for name in _TRACED_EFFECTS:
            if name in names:
                raise SpecError(path, "render.effects", f"{name!r} comes out of the compound lens's ray tracing "
                                "(lens.prescription); remove it from the list")
        if aperture.get("shape", "circle") != "circle":
            raise SpecError(path, "lens.aperture", "a compound lens's stop is round; polygon and anamorphic "
                            "apertures are for the thin lens")
    else:
        for key, why in (("focus_plane", "a thin lens has no aberration, its best and paraxial focus coincide"),
                         ("focusing", "a thin lens has no groups to move; it focuses by moving as a whole"),
                         ("focus_group", "a thin lens has no groups to move; it focuses by moving as a whole"),
                         ("wavelengths_nm", "a thin lens has no glass; its colour errors are the "
                          "chromatic_aberration effect"),
                         ("colour", "it asks for colour from the spectral samples of lens.wavelengths_nm")):
            if key in lens:
                raise SpecError(path, f"lens.{key}", f"applies to a compound lens (lens.prescription) only: {why}; "
                                "remove it")
    wavelengths = _wavelengths(lens, path, rx, effects) if rx is not None else ()
    internal = _internal_focusing(lens, path, rx, wavelengths) if rx is not None else None
    fmt = render.get("format", "dng" if effects.mosaic is not None else DEFAULTS["format"])
    problem = effects.format_problem(fmt)
    if problem is not None:
        raise SpecError(path, "render.format", f"got {fmt!r}: must be {problem[0]}; {problem[1]}")
    settings = RenderSettings(
        effects=names, method=render.get("method", DEFAULTS["method"]),
        samples_per_pixel=int(render.get("samples_per_pixel", DEFAULTS["samples_per_pixel"])),
        supersampling=int(render.get("supersampling", DEFAULTS["supersampling"])),
        seed=int(render.get("seed", DEFAULTS["seed"])), format=fmt,
        jpeg_quality=int(render.get("jpeg_quality", DEFAULTS["jpeg_quality"])),
        mitsuba_variant=render.get("mitsuba_variant", DEFAULTS["mitsuba_variant"]))

    targets = [_target(i, o, path, f) for i, o in enumerate(data["object"])]
    ids = [t.id for t in targets]
    for i, t in enumerate(targets):
        if ids.index(t.id) != i:
            raise SpecError(path, f"object[{i}].id", f"got {t.id!r}: ids must be unique")
    base_pose = {t.id: o for t, o in zip(targets, data["object"])}

    def focus(value, where):
        D = _distance(value)
        if not D > f:
            raise SpecError(path, where, f"got {value}: the focus distance must be beyond the focal length "
                            f"({f:g} mm)")
        return D

    lens_N, lens_D = float(lens["f_number"]), focus(lens["focus_distance_mm"], "lens.focus_distance_mm")
    shots_spec = data.get("shot") or [{}]
    shots: list[Shot] = []
    setting_values: dict[str, tuple[float, float, int]] = {}
    for k, sh in enumerate(shots_spec):
        where = f"shot[{k}]"
        N = float(sh.get("f_number", lens_N))
        D = focus(sh["focus_distance_mm"], f"{where}.focus_distance_mm") if "focus_distance_mm" in sh else lens_D
        label = sh.get("setting", "a")
        if label in setting_values and setting_values[label][:2] != (N, D):
            first = setting_values[label][2]
            raise SpecError(path, f"{where}.setting", f"got {label!r}: shot[{first}] has the same setting with "
                            f"f_number {setting_values[label][0]:g} and focus_distance_mm {setting_values[label][1]:g}; "
                            "shots sharing a setting label must share f-number and focus distance")
        lens_here, f_here, N_here, shift = rx, f, N, None
        if internal is not None:  # the group moved to focus D: this setting's own lens, EFL and f-number
            lens_here, shift = internal(N, D, f"{where}.focus_distance_mm" if "focus_distance_mm" in sh
                                        else "lens.focus_distance_mm")
            from synth.lens import paraxial

            para = paraxial(lens_here)
            f_here, N_here = para.efl_mm, para.efl_mm / para.entrance_pupil_diameter_mm
        if rx is not None and label not in setting_values:
            _check_opens(path, f"{where}.f_number" if "f_number" in sh else "lens.f_number", lens_here, N_here, D)
        setting_values.setdefault(label, (N, D, k))
        overrides = {}
        for j, pose in enumerate(sh.get("pose", [])):
            if pose["id"] not in base_pose:
                raise SpecError(path, f"{where}.pose[{j}].id", f"got {pose['id']!r}: no object has this id; "
                                f"valid: {', '.join(ids)}")
            overrides[pose["id"]] = pose
        visible = sh.get("objects", ids)
        for j, oid in enumerate(visible):
            if oid not in base_pose:
                raise SpecError(path, f"{where}.objects[{j}]", f"got {oid!r}: no object has this id; valid: {', '.join(ids)}")
        placed = []
        for t in targets:
            if t.id not in visible:
                continue
            spec = {**base_pose[t.id], **overrides.get(t.id, {})}
            pose = Pose.from_spec(float(spec["distance_mm"]), spec.get("tilt_deg", [0.0, 0.0]),
                                  spec.get("offset_mm", [0.0, 0.0]))
            fld = f"{where}.pose" if t.id in overrides else f"object[{ids.index(t.id)}]"
            _check_in_front(path, f"{fld}.distance_mm", t, pose, f)
            placed.append(PlacedObject(t, pose))
        if rx is None:
            camera = ThinLensCamera(focal_length_mm=f, f_number=N, focus_distance_mm=D, pixel_pitch_mm=pitch,
                                    width_px=int(cam["width_px"]), height_px=int(cam["height_px"]))
        else:
            camera = CompoundLensCamera(focal_length_mm=f_here, f_number=N_here, focus_distance_mm=D,
                                        pixel_pitch_mm=pitch,
                                        width_px=int(cam["width_px"]), height_px=int(cam["height_px"]),
                                        prescription=lens_here, focus_plane=lens.get("focus_plane", "best"),
                                        wavelengths_nm=wavelengths,
                                        focus_group=None if shift is None else tuple(lens["focus_group"]),
                                        focus_group_shift_mm=shift)
        if ("shutter_s" in sh or "iso" in sh) and effects.exposure is None:
            raise SpecError(path, f"{where}.{'shutter_s' if 'shutter_s' in sh else 'iso'}",
                            "is an exposure setting, but 'exposure' is not in render.effects; add it or remove this")
        shots.append(Shot(name=sh.get("name", f"shot_{k:03d}"), setting=label, camera=camera, objects=tuple(placed),
                          shutter_s=sh.get("shutter_s"), iso=sh.get("iso")))
    names = [s.name for s in shots]
    if len(set(names)) != len(names):
        raise SpecError(path, "shot", "shot names must be unique")
    return Scene(path=str(path), name=data.get("name", Path(str(path)).stem), pixel_pitch_mm=pitch,
                 width_px=int(cam["width_px"]), height_px=int(cam["height_px"]), focal_length_mm=f,
                 aperture=aperture, render=settings,
                 background_value=float(data.get("background", {}).get("value", DEFAULTS["background"])),
                 targets=tuple(targets), shots=tuple(shots), effects=effects)
