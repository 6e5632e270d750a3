"""The samples CSV that ``lensfit measure`` writes: its columns, and the file read back (rows with
numbers parsed, and the calibration, pixel pitch and focal length in px per setting, that its rows
repeat). :class:`lensfit.io.samples.SampleTable` writes it."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from lensfit.errors import SpecError

#: The header line ``lensfit measure`` writes to a samples CSV (lensfit.io.samples.SampleTable.COLUMNS).
SAMPLES_CSV_COLUMNS = ("image", "setting", "target", "edge", "distance_mm", "coc_diameter_px", "sigma_px",
                       "estimator", "flags", "distance_start_mm", "distance_end_mm", "start_px", "end_px",
                       "distance_source", "field_radius_px", "disk_diameter_px", "disk_sigma_px")
#: Headers earlier versions wrote (their files are lensfit's to replace with --force): without
#: disk_diameter_px and disk_sigma_px, and without field_radius_px too.
SAMPLES_CSV_EARLIER = (SAMPLES_CSV_COLUMNS[:-2], SAMPLES_CSV_COLUMNS[:-3])
#: The calibration columns after them (each row repeats its setting's calibration, so that a
#: refit from the CSV alone equals the fit from the stack), with the radial
#: distortion the calibration fitted (OpenCV's k1, k2; blank where the intrinsics were given),
#: which the fit's error budget reads (lensfit.fitting.constants.BLUR_SCALE_SIGMA_PLAIN).
SAMPLES_CSV_CALIBRATION = ("pixel_pitch_mm", "focal_length_px", "focal_length_sigma_px", "distortion_k1",
                           "distortion_k2")
SAMPLES_CSV_CALIBRATION_EARLIER = SAMPLES_CSV_CALIBRATION[:3]
#: Columns that hold numbers (blank: no value).
SAMPLES_CSV_NUMERIC = ("distance_mm", "distance_start_mm", "distance_end_mm", "coc_diameter_px", "sigma_px",
                       "field_radius_px", "disk_diameter_px", "disk_sigma_px", *SAMPLES_CSV_CALIBRATION)
#: Columns every samples CSV has (also one written by hand for ``lensfit fit``).
SAMPLES_CSV_REQUIRED = ("setting", "distance_mm", "coc_diameter_px", "sigma_px")


def read_samples_csv(path: str | Path) -> list[dict[str, Any]]:
    """Rows of a samples CSV written by ``lensfit measure`` (numbers parsed, blanks None)."""
    path = Path(path)
    try:
        return _read_samples_csv(path)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise SpecError(path, "", f"not a readable CSV ({exc}); write samples with lensfit measure") from None


#: Rows a samples CSV may hold (a stack of hundreds of images has some tens of thousands of
#: edges); the bytes checked first, so that a larger file is refused before it is read.
MAX_ROWS = 1_000_000
MAX_BYTES = 256 * 1024 * 1024


def _read_samples_csv(path: Path) -> list[dict[str, Any]]:
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise SpecError(path, "", f"is {size / 1e6:.0f} MB, more than the {MAX_BYTES / 1e6:.0f} MB of a samples CSV "
                        "lensfit reads; is it the file you meant?")
    rows = []
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        names = reader.fieldnames or []
        twice = sorted({c for c in names if names.count(c) > 1})
        if twice:
            raise SpecError(path, twice[0], "column appears twice in the header; one value per column")
        missing = [c for c in SAMPLES_CSV_REQUIRED if c not in names]
        if missing:
            raise SpecError(path, missing[0], "column missing; write samples with lensfit measure")
        for i, r in enumerate(reader, start=2):
            if i - 1 > MAX_ROWS:
                raise SpecError(path, "", f"holds more than {MAX_ROWS} rows; split the stack")
            if None in r or any(v is None for v in r.values()):
                raise SpecError(path, f"line {i}", f"has {len(names) + len(r.get(None) or [])} cells where the header "
                                f"has {len(names)} columns; one cell per column")
            if any("\x00" in (v or "") for v in r.values()):
                raise SpecError(path, f"line {i}", "holds a NUL byte; a samples CSV is text")
            row: dict[str, Any] = dict(r)
            for c in SAMPLES_CSV_NUMERIC:
                if c in row:
                    v = (row[c] or "").strip()
                    try:
                        row[c] = float(v) if v else None
                    except ValueError:
                        raise SpecError(path, f"line {i}: {c}", f"{v!r} is not a number") from None
                    if row[c] is not None and not math.isfinite(row[c]):
                        raise SpecError(path, f"line {i}: {c}", f"{v!r} is not a finite number; leave the cell "
                                        "empty where an edge has no measurement")
            for c in ("start_px", "end_px"):
                v = (row.get(c) or "").strip()
                if v:
                    try:
                        row[c] = tuple(float(x) for x in v.split())
                    except ValueError:
                        row[c] = ()
                    if len(row[c]) != 2 or not all(math.isfinite(x) for x in row[c]):
                        raise SpecError(path, f"line {i}: {c}", f"{v!r} is not two finite pixel coordinates "
                                        "\"x y\"; leave the cell empty where they are not known")
            rows.append(row)
    return rows


def csv_calibration(path: Path, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The pixel pitch and per-setting focal lengths (and, where a calibration fitted them, its
    radial distortion k1, k2) a samples CSV repeats on its rows (empty where the columns are
    absent); rows of one setting must agree."""
    from lensfit.io.limits import DISTORTION_MAX, INTRINSICS_MAX_PX

    bounds = {"focal_length_px": (0.0, INTRINSICS_MAX_PX), "focal_length_sigma_px": (0.0, INTRINSICS_MAX_PX),
              "distortion_k1": (-DISTORTION_MAX, DISTORTION_MAX), "distortion_k2": (-DISTORTION_MAX, DISTORTION_MAX)}
    for i, r in enumerate(rows, start=2):
        for column, (lo, hi) in bounds.items():
            v = r.get(column)
            if v is not None and not (lo <= v <= hi and (v > 0 or column != "focal_length_px")):
                raise SpecError(path, f"line {i}: {column}", f"got {v!r}; expected a number from {lo:g} to {hi:g} "
                                "(write samples with lensfit measure)")
    out: dict[str, Any] = {}
    pitches = {r["pixel_pitch_mm"] for r in rows if r.get("pixel_pitch_mm") is not None}
    if len(pitches) > 1:
        raise SpecError(path, "pixel_pitch_mm", f"rows disagree ({sorted(pitches)[:2]}); one stack has one pitch")
    if pitches:
        out["pixel_pitch_mm"] = pitches.pop()
    intrinsics: dict[str, dict[str, Any]] = {}
    for i, r in enumerate(rows, start=2):
        if r.get("focal_length_px") is None:
            continue
        entry = {"focal_length_px": r["focal_length_px"], "source": "samples CSV",
                 "focal_length_sigma_px": r.get("focal_length_sigma_px") or 0.0}
        if r.get("distortion_k1") is not None and r.get("distortion_k2") is not None:  # a calibration's fit
            entry.update(source="calibrated", distortion=[r["distortion_k1"], r["distortion_k2"], 0.0, 0.0, 0.0])
        first = intrinsics.setdefault(str(r["setting"]), entry)
        for column, key, at in (("focal_length_px", "focal_length_px", None),
                                ("focal_length_sigma_px", "focal_length_sigma_px", None),
                                ("distortion_k1", "distortion", 0), ("distortion_k2", "distortion", 1)):
            mine, earlier = entry.get(key), first.get(key)
            if at is not None:
                mine, earlier = (None if mine is None else mine[at]), (None if earlier is None else earlier[at])
            if mine != earlier:
                raise SpecError(path, f"line {i}: {column}", f"{mine} differs from the earlier {earlier} of setting "
                                f"{r['setting']!r}; a setting has one calibration, which every row repeats")
    if intrinsics:
        out["intrinsics"] = intrinsics
    return out
