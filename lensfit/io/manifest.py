"""Drafting ``stack.toml`` from a folder of photos (``lensfit init``).

What it needs and where it comes from:

- **images**: every PNG, TIFF, JPEG, DNG and camera RAW file directly in the folder, in name
  order. Where a camera wrote RAW + JPEG pairs (same name stem) the RAW file is listed (linear,
  no tone curve) unless ``prefer="jpeg"``.
- **settings** (images with one label share focus distance and f-number): by default the
  distinct (focal length, f-number, focus distance) the EXIF records, labelled ``a``, ``b``, ...
  in order of first appearance. Without a focus distance in the EXIF (most cameras write
  none; ``SubjectDistance`` or Canon's maker note where they do) photos refocused between
  shots cannot be told apart: the draft says so and the labels must be checked.
  ``grouping="per-image"`` gives every image its own label; ``"one"`` one label for all.
- **pixel pitch**: an explicit value, sensor width or sensor format first; then the EXIF
  ``FocalPlaneXResolution`` (scaled to the image's width where the file was resized); then the
  camera body in ``data_specs/cameras.toml`` (sensor width / image width). Otherwise refused.
- **targets**: ``[[target]]`` tables from a TOML file (what ``lensfit target --entry`` writes,
  or another stack.toml); without one, the board ``lensfit target`` draws by default, noted
  as an assumption.

The EXIF values are kept beside each image as ``x_exif`` (never read by the fit: they are
nominal values, never the answer). Nothing is written here: :func:`draft_manifest` returns
the text, the CLI writes it.
"""

from __future__ import annotations

import functools
import math
import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lensfit.errors import InputError, SpecError
from lensfit.io.exif import CameraRecord, read_camera_record
from lensfit.measurement.processing import developer_of
from lensfit.io.images import JPEG_SUFFIXES, RASTER_SUFFIXES, RAW_SUFFIXES, image_size

GROUPINGS = ("exif", "per-image", "one")
#: A resized copy (web export) changes the width FocalPlaneXResolution refers to; a RAW
#: decoder's crop of a few pixels does not.
_RESIZED = 0.02
#: First line of a drafted stack.toml (``lensfit.outputs.writers.written_by`` recognises it).
HEADER = "# Written by lensfit init"


@dataclass
class Draft:
    """A drafted manifest: ``text`` (stack.toml), ``manifest`` (the same as a dict), one row
    per image for a table (``rows``) and ``notes`` (what was assumed and what to check)."""

    text: str
    manifest: dict[str, Any]
    rows: list[dict[str, Any]]
    notes: list[str] = field(default_factory=list)


@functools.cache
def known_cameras() -> list[dict[str, Any]]:
    """``data_specs/cameras.toml``, validated."""
    from lensfit.io.specs import load_toml, specs_dir, validate

    path = specs_dir() / "cameras.toml"
    data = load_toml(path)
    validate(data, "cameras", path)
    return data["camera"]


def camera_sensor(record: CameraRecord) -> dict[str, Any] | None:
    """The entry of ``data_specs/cameras.toml`` for a photo's Make and Model, or None."""
    if not record.model:
        return None
    make = (record.make or "").strip().lower()
    model = record.model.strip().lower()
    for entry in known_cameras():
        emake = entry["make"].lower()
        if make and not make.startswith(emake):
            continue
        bare = model.removeprefix(emake).strip()
        names = [entry["model"].lower(), *(a.lower() for a in entry.get("aliases", []))]
        if bare in names or model in names:
            return entry
    return None


def shown(text: str) -> str:
    """``text`` (a file name, an EXIF string) safe for a terminal and a TOML comment: control
    characters (newlines, escape sequences) and undecodable bytes written as escapes."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape", "backslashreplace").decode("ascii")
                   for c in text)


def _valid_name(p: Path) -> bool:
    try:
        p.name.encode("utf-8")
    except UnicodeEncodeError:  # undecodable bytes (surrogate escapes) in the file system's name
        return False
    return True


def photo_files(folder: Path, prefer: str = "raw") -> tuple[list[Path], list[str]]:
    """Image files directly in ``folder`` (name order) and the names left out as the other half
    of a RAW + JPEG pair. Symbolic links that lead out of the folder are refused, as are names
    that are not valid UTF-8 (stack.toml could not name them)."""
    if prefer not in ("raw", "jpeg"):
        raise InputError("prefer", prefer, "raw or jpeg")
    inside = folder.resolve()
    files = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or p.suffix.lower() not in RAW_SUFFIXES | RASTER_SUFFIXES:
            continue
        if not _valid_name(p):
            raise InputError("photos", shown(str(p)), "a folder of image files named in UTF-8 (stack.toml names each "
                             "file)", "rename the file")
        if not p.resolve().is_relative_to(inside):
            raise InputError("photos", shown(str(p)), "a folder whose image files lie inside it",
                             f"it is a link to {shown(str(p.resolve()))}, outside {shown(str(folder))}: copy the "
                             "photo into the folder instead")
        if p.is_file():
            files.append(p)
    by_stem: dict[str, list[Path]] = {}
    for p in files:
        by_stem.setdefault(p.stem, []).append(p)
    keep, skipped = [], []
    for p in files:
        group = by_stem[p.stem]
        raws = [q for q in group if q.suffix.lower() in RAW_SUFFIXES]
        jpegs = [q for q in group if q.suffix.lower() in JPEG_SUFFIXES]
        if raws and jpegs and p in (jpegs if prefer == "raw" else raws):
            skipped.append(p.name)
            continue
        keep.append(p)
    return keep, skipped


def _label(i: int) -> str:
    """Setting labels a, b, ..., z, aa, ab, ..., zz, aaa, ... (bijective base 26)."""
    letters, out = string.ascii_lowercase, ""
    i += 1
    while i:
        i, r = divmod(i - 1, 26)
        out = letters[r] + out
    return out


def _round(x: float | None, digits: int = 4) -> float | None:
    return None if x is None else float(f"{x:.{digits}g}")


def _pitch(records: list[CameraRecord], files: list[Path], width_px: int, pixel_pitch_mm: float | None,
           sensor: str | None, sensor_width_mm: float | None, folder: Path) -> tuple[dict[str, Any], str]:
    """stack.toml's [camera] table and where its pitch comes from."""
    given = {k: v for k, v in (("pixel_pitch_mm", pixel_pitch_mm), ("sensor", sensor),
                               ("sensor_width_mm", sensor_width_mm)) if v is not None}
    if len(given) > 1:
        first, second = list(given)[:2]
        raise InputError(second, given[second], f"given alone (also got {first})",
                         "give one of pixel pitch, sensor format or sensor width")
    if pixel_pitch_mm is not None:
        return {"pixel_pitch_mm": float(pixel_pitch_mm)}, "given"
    if sensor_width_mm is not None:
        return {"sensor_width_mm": float(sensor_width_mm)}, "given"
    if sensor is not None:
        from lensfit.io.sensors import sensor_format

        return {"sensor": sensor_format(sensor).name}, "given"
    pitches = []
    for r, f in zip(records, files):
        if r.focal_plane_pitch_mm is None:
            continue
        p = r.focal_plane_pitch_mm
        resizable = f.suffix.lower() in RASTER_SUFFIXES  # RAW files are never resized
        if resizable and r.reference_width_px and abs(r.reference_width_px / width_px - 1) > _RESIZED:
            p *= r.reference_width_px / width_px  # a resized copy: the same sensor, fewer pixels
        pitches.append(p)
    if pitches:
        pitches.sort()
        p = pitches[len(pitches) // 2]
        return {"pixel_pitch_mm": float(f"{p:.6g}")}, "EXIF FocalPlaneXResolution"
    for r in records:
        entry = camera_sensor(r)
        if entry is not None:
            return ({"sensor_width_mm": float(entry["sensor_width_mm"])},
                    f"{r.camera} in data_specs/cameras.toml ({entry['sensor_width_mm']:g} mm wide)")
    cams = sorted({r.camera for r in records if r.camera})
    raise InputError("pixel_pitch_mm", None, "known",
                     f"the photos in {folder} do not record it (no EXIF FocalPlaneXResolution) and the camera "
                     f"({', '.join(cams) or 'not named in the EXIF'}) is not in data_specs/cameras.toml; "
                     "pass --pixel-pitch MM, --sensor-width MM or --sensor NAME")


def target_entries(target_file: Path | None) -> tuple[list[dict[str, Any]], str | None]:
    """The [[target]] tables of a TOML file (``lensfit target --entry``, or a stack.toml), or
    without one the board ``lensfit target`` draws by default with a note saying it was assumed."""
    if target_file is None:
        from lensfit.capture.printable import charuco_page

        entry = charuco_page().entry  # what `lensfit target --out board.pdf` draws
        return [entry], ("no --target given: assumed the board `lensfit target` draws by default "
                         f"({entry['squares'][0]} x {entry['squares'][1]} squares of {entry['square_mm']:g} mm on "
                         "A4 landscape); measure a printed square and correct square_mm and marker_mm")
    from lensfit.io.specs import load_toml

    data = load_toml(target_file)
    targets = data.get("target")
    if not isinstance(targets, list) or not targets:
        raise SpecError(target_file, "target", "no [[target]] tables; give the entry `lensfit target --entry FILE` "
                        "wrote (or a stack.toml with one)")
    return targets, None


#: A measured square may differ from the drawn one by at most this ratio either way (printers
#: scale by a few per cent; more is a unit slip or a different board).
MEASURED_SQUARE_RATIO = 1.25


def as_measured(targets: list[dict[str, Any]], measured_square_mm: float | None) -> tuple[list[dict[str, Any]], str]:
    """The targets with the printed board's ``square_mm`` replaced by the measured side and its
    ``marker_mm`` scaled with it, and a note saying so (or, without a measurement, asking for one)."""
    boards = [t for t in targets if t.get("kind") == "charuco"]
    if measured_square_mm is None:
        if not boards:
            return targets, ""
        drawn = float(boards[0]["square_mm"])
        return targets, (f"measure a printed square with a ruler: where it is not {drawn:g} mm, run lensfit init "
                         "again with --measured-square-mm MM (distances, and so the focus distance, scale with the "
                         "board)")
    if len(boards) != 1:
        raise InputError("measured_square_mm", measured_square_mm, "given for exactly one printed ChArUco board",
                         f"the target file has {len(boards)}; set square_mm and marker_mm of each in stack.toml")
    board = boards[0]
    drawn = float(board["square_mm"])
    ratio = measured_square_mm / drawn
    if not (math.isfinite(ratio) and 1 / MEASURED_SQUARE_RATIO <= ratio <= MEASURED_SQUARE_RATIO):
        raise InputError("measured_square_mm", measured_square_mm, f"within {100 * (MEASURED_SQUARE_RATIO - 1):.0f} % "
                         f"of the {drawn:g} mm the board was drawn with", "measure one square's side in millimetres "
                         "(a printer scales by a few per cent)")
    scaled = dict(board, square_mm=float(measured_square_mm), marker_mm=round(float(board["marker_mm"]) * ratio, 6))
    return ([scaled if t is board else t for t in targets],
            f"target '{board.get('id')}': square_mm {measured_square_mm:g} as measured (drawn {drawn:g} mm: printed at "
            f"{100 * ratio:.1f} %), marker_mm scaled with it to {scaled['marker_mm']:g}")


def draft_manifest(folder: str | Path, *, target_file: str | Path | None = None,
                   pixel_pitch_mm: float | None = None, sensor: str | None = None,
                   sensor_width_mm: float | None = None, grouping: str = "exif", prefer: str = "raw",
                   max_pixels: int | None = None, measured_square_mm: float | None = None) -> Draft:
    """Draft stack.toml for the photos in ``folder`` (see the module notes).

    Raises
    ------
    InputError
        No images, images of different sizes or focal lengths, no way to know the pixel pitch.
    SpecError
        A bad target file, or a draft that does not validate (a bug: reported, not written).
    """
    from lensfit.io.limits import DEFAULT_MAX_MEGAPIXELS
    from lensfit.io.specs import validate

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("photos", str(folder), "a folder of photos", "give the folder that holds the images")
    if grouping not in GROUPINGS:
        raise InputError("settings", grouping, "one of " + ", ".join(GROUPINGS))
    files, skipped = photo_files(folder, prefer)
    if not files:
        raise InputError("photos", str(folder), "a folder holding PNG, TIFF, JPEG, DNG or camera RAW files",
                         "copy the photos of the target into it")
    from lensfit.io.stack import MAX_IMAGES

    if len(files) > MAX_IMAGES:  # (before any file is opened: stack.toml could not list them)
        raise InputError("photos", f"{len(files)} image files in {shown(str(folder))}", f"at most {MAX_IMAGES}, what "
                         "one stack may list", "put each stack's photos in a folder of their own")
    turned, upright, (_, width) = _photo_sizes(files, folder, max_pixels or int(DEFAULT_MAX_MEGAPIXELS * 1e6))
    records = [read_camera_record(p) for p in files]
    _one_focal_length(files, records, folder)
    notes = []
    if turned:
        notes.append(f"{len(turned)} portrait photo(s) (e.g. {turned[0].name}, {upright[0]} x {upright[1]} px against "
                     f"{upright[1]} x {upright[0]}) are turned back on reading with rotate_deg = 90; where the camera "
                     "was turned the other way, write 270 (the calibration's principal point depends on it)")
    if skipped:
        notes.append(f"{len(skipped)} {'JPEG' if prefer == 'raw' else 'RAW'} file(s) of RAW + JPEG pairs left out "
                     f"(e.g. {skipped[0]}); --prefer {'jpeg' if prefer == 'raw' else 'raw'} lists those instead")
    developed = [(p, developer_of(p, r)) for p, r in zip(files, records)]
    developed = [(p, name) for p, name in developed if name]
    if developed:
        notes.append(f"{len(developed)} photo(s) were developed ({developed[0][1]}, e.g. {developed[0][0].name}): a "
                     "tone curve and sharpening read the f-number 5-20 % high, and lensfit fit refuses it from them; "
                     "give the RAW files, or linear TIFF exported without sharpening")
    camera, pitch_source = _pitch(records, files, width, pixel_pitch_mm, sensor, sensor_width_mm, folder)
    notes.append(f"pixel pitch: {pitch_source}")
    targets, target_note = target_entries(Path(target_file) if target_file is not None else None)
    targets, measured_note = as_measured(targets, measured_square_mm)
    notes += [note for note in (target_note, measured_note) if note]

    keys, labels = _setting_keys(records, grouping, notes)
    images = [_image_entry(p, r, labels[k], p in turned, notes) for p, r, k in zip(files, records, keys)]
    rows = [{"file": p.name, "setting": labels[k], "focal_length_mm": r.focal_length_mm, "f_number": r.f_number,
             "focus_distance_mm": r.focus_distance_mm} for p, r, k in zip(files, records, keys)]
    manifest = {"camera": camera, "target": targets, "image": images}
    widest = [r.widest_f_number for r in records if r.widest_f_number]
    if widest:
        # The largest any photo states: the fewer stops below it each setting counts, the wider
        # the spread of real designs it carries.
        manifest["lens"] = {"widest_f_number": max(widest)}
        notes.append(f"[lens] widest_f_number {max(widest):g}: the lens's full aperture, from EXIF "
                     "MaxApertureValue (or LensSpecification); settings stopped down from it carry a narrower spread "
                     "of real lens designs in f and N")
    validate(manifest, "stack", folder / "stack.toml")
    return Draft(manifest_text(manifest, notes, folder), manifest, rows, notes)


def _photo_sizes(files: list[Path], folder: Path, max_pixels: int):
    """The photos turned by an export, the sensor's upright (height, width) and the one shape all
    share once turned back (an InputError where they differ, or a photo exceeds ``max_pixels``)."""
    from lensfit.io.limits import check_image_size

    sizes = {}
    for p in files:
        sizes[p] = image_size(p)
        check_image_size(p, *sizes[p], max_pixels)
    # Portrait photos whose pixels were turned (an export that applied the EXIF orientation) have
    # the others' width and height swapped: turned back on reading (rotate_deg), the sensor's
    # orientation taken as the one most photos have.
    counts = {shape: sum(1 for v in sizes.values() if v == shape) for shape in set(sizes.values())}
    upright = max(counts, key=lambda shape: (counts[shape], shape[1] >= shape[0]))
    turned = [p for p in files if sizes[p] == (upright[1], upright[0]) and upright[0] != upright[1]]
    for p in turned:
        sizes[p] = upright
    shapes = sorted(set(sizes.values()))
    if len(shapes) > 1:
        odd = next(p for p in files if sizes[p] != sizes[files[0]])
        raise InputError("photos", str(folder), "images of one size (one camera, one crop)",
                         f"{files[0].name} is {sizes[files[0]][1]} x {sizes[files[0]][0]} px but {odd.name} is "
                         f"{sizes[odd][1]} x {sizes[odd][0]}; move the odd ones to another folder")
    return turned, upright, shapes[0]


def _one_focal_length(files: list[Path], records: list, folder: Path) -> None:
    """An InputError where the photos' EXIF records more than one focal length (one lens per stack)."""
    focals = sorted({_round(r.focal_length_mm, 3) for r in records if r.focal_length_mm})
    if len(focals) > 1:
        by = {f: [p.name for p, r in zip(files, records) if _round(r.focal_length_mm, 3) == f] for f in focals}
        raise InputError("photos", str(folder), "one focal length (a stack fits one lens: a zoom at two focal "
                         "lengths is two lenses)", "; ".join(f"{f:g} mm: {', '.join(v[:3])}" + (" ..." if len(v) > 3
                                                                                                   else "")
                                                             for f, v in by.items()) + "; split them into folders")


def _setting_keys(records: list, grouping: str, notes: list[str]) -> tuple[list, dict]:
    """Each photo's setting key by ``grouping`` and the keys' labels; notes where the EXIF leaves
    the grouping in doubt."""
    keys = []
    for i, r in enumerate(records):
        if grouping == "per-image":
            keys.append(i)
        elif grouping == "one":
            keys.append(0)
        else:
            keys.append((_round(r.f_number, 3), _round(r.focus_distance_mm, 3)))
    labels = {k: _label(n) for n, k in enumerate(dict.fromkeys(keys))}
    if grouping == "exif":
        if any(r.f_number is None for r in records):
            notes.append("some photos record no f-number: they share a setting only with others that record none")
        if all(r.focus_distance_mm is None for r in records):
            notes.append("the EXIF records no focus distance: photos are grouped by f-number alone; if you refocused "
                         "between shots, give those photos different setting labels (or --settings per-image)")
    return keys, labels


def _image_entry(p: Path, r: Any, label: str, turned: bool, notes: list[str]) -> dict[str, Any]:
    """A photo's [[image]] entry (file, rotation, encoding, setting, the EXIF as x_exif)."""
    entry: dict[str, Any] = {"file": p.name}
    if turned:
        entry["rotate_deg"] = 90
    if p.suffix.lower() in JPEG_SUFFIXES:
        entry["encoding"] = "srgb"
    elif p.suffix.lower() in (".png", ".tif", ".tiff"):
        entry["encoding"] = "linear"
        notes_png = "PNG/TIFF files are read as linear (encoding = \"linear\"); write \"srgb\" for exported, " \
                    "tone-mapped images"
        if notes_png not in notes:
            notes.append(notes_png)
    entry["setting"] = label
    exif = {name: value for name, value in (
        ("camera", r.camera), ("focal_length_mm", _round(r.focal_length_mm)), ("f_number", _round(r.f_number)),
        ("focus_distance_mm", _round(r.focus_distance_mm) if r.focus_distance_mm not in (None, float("inf"))
         else ("inf" if r.focus_distance_mm else None)),
        ("shutter_s", _round(r.shutter_s)), ("iso", _round(r.iso)), ("taken", r.taken))
        if value is not None}
    exif = {name: shown(value) if isinstance(value, str) else value for name, value in exif.items()}
    if exif:
        entry["x_exif"] = exif
    return entry


def manifest_text(manifest: dict[str, Any], notes: list[str], folder: Path) -> str:
    """stack.toml: the header (with the notes as comments), [camera], [[target]]s, [[image]]s."""
    import tomli_w

    from lensfit import __version__

    lines = [f"{HEADER} {__version__} from the EXIF of the photos in {shown(folder.name)}/.",
             "# Only what a photographer knows (never the answer): check the setting labels -- images with one",
             "# label share focus distance and f-number -- and the target's printed size.",
             "# x_exif: what each file's EXIF says (nominal values; never read by the fit)."]
    lines += [f"# Note: {shown(n)}" for n in notes]
    text = "\n".join(lines) + "\n\n[camera]\n" + tomli_w.dumps(manifest["camera"])
    if manifest.get("lens"):
        text += "\n[lens]\n" + tomli_w.dumps(manifest["lens"])
    for section in ("target", "image"):
        for entry in manifest[section]:
            plain = {k: v for k, v in entry.items() if not isinstance(v, dict)}
            text += f"\n[[{section}]]\n" + tomli_w.dumps(plain)
            for key, table in entry.items():  # inline: a [sub-table] header here would leave the entry
                if isinstance(table, dict):
                    items = ", ".join(tomli_w.dumps({k: v}).strip() for k, v in table.items())
                    text += f"{key} = {{ {items} }}\n"
    return text
