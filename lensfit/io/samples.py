"""The samples a measure gives: one blur reading per target edge and image (:class:`Sample`), and
the table of them with what was learnt on the way (:class:`SampleTable`: intrinsics, poses,
detections; written as CSV or JSON and read back). :func:`lensfit.measurement.measure.measure` makes them."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from lensfit.calibration.camera import Intrinsics, TargetPose
from lensfit.errors import InputError, SpecError
from lensfit.estimators.base import Flag, flags_from_text
from lensfit.io.samples_csv import SAMPLES_CSV_CALIBRATION, SAMPLES_CSV_COLUMNS, csv_calibration, read_samples_csv
from lensfit.outputs.writers import provenance


@dataclass(frozen=True)
class Sample:
    """One blur measurement on one target edge in one image."""

    image: str
    setting: str
    target: str
    edge: str
    distance_mm: float  # of the edge's middle, from the lens plane
    distance_start_mm: float
    distance_end_mm: float
    coc_diameter_px: float | None
    sigma_px: float | None
    estimator: str
    flags: tuple[Flag, ...]  # written ";"-separated
    start_px: tuple[float, float]
    end_px: tuple[float, float]
    distance_source: str  # "pose" or "manifest"
    #: distance of the edge's middle from its setting's principal point (px; None: not known)
    field_radius_px: float | None = None
    #: where the reading is a shaped spot's, the uniform disk's reading of the same edge and its sigma (px)
    disk_diameter_px: float | None = None
    disk_sigma_px: float | None = None

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> "Sample":
        """A sample from its columns by name (a samples file's row, or a caller's mapping):
        numbers as numbers or text, ``flags`` as members or ``;``-separated names, the end
        points as pairs or ``"x y"`` text. Only ``setting`` and ``distance_mm`` are required; the
        edge's ends default to its middle. An unreadable value raises
        :class:`lensfit.errors.InputError` naming its column."""
        for name in ("setting", "distance_mm"):
            if given_or(row.get(name), None) is None:
                raise InputError(name, None, "present")
        distance = _number(row, "distance_mm")
        flags = row.get("flags") or ()
        try:
            flags = flags_from_text(flags) if isinstance(flags, str) else tuple(Flag(f) for f in flags)
        except (TypeError, ValueError) as exc:
            raise InputError("flags", flags, "flags lensfit writes", str(exc)) from None
        return cls(image=_text(row, "image"), setting=_text(row, "setting"), target=_text(row, "target"),
                   edge=_text(row, "edge"), distance_mm=distance,
                   distance_start_mm=_number(row, "distance_start_mm", distance),
                   distance_end_mm=_number(row, "distance_end_mm", distance),
                   coc_diameter_px=_number(row, "coc_diameter_px", None), sigma_px=_number(row, "sigma_px", None),
                   estimator=_text(row, "estimator"), flags=flags, start_px=_point(row, "start_px"),
                   end_px=_point(row, "end_px"), distance_source=_text(row, "distance_source"),
                   field_radius_px=_number(row, "field_radius_px", None),
                   disk_diameter_px=_number(row, "disk_diameter_px", None),
                   disk_sigma_px=_number(row, "disk_sigma_px", None))


_REQUIRED = object()


def _text(row: Mapping[str, Any], name: str) -> str:
    return str(given_or(row.get(name), ""))


def _number(row: Mapping[str, Any], name: str, default: Any = _REQUIRED) -> Any:
    """A column's value as a float (``default`` where it was left out)."""
    value = given_or(row.get(name), default)
    if value is default and default is not _REQUIRED:
        return default
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(name, value, "a number" + ("" if default is _REQUIRED else ", or left out")) from None


def _point(row: Mapping[str, Any], name: str) -> tuple[float, float]:
    """An image point, ``(x, y)`` px, from a pair or ``"x y"`` text; (0, 0) where left out."""
    value = given_or(row.get(name), (0.0, 0.0))
    try:
        point = tuple(float(v) for v in (value.split() if isinstance(value, str) else value))
    except (TypeError, ValueError):
        point = ()
    if len(point) != 2:
        raise InputError(name, value, "two pixel coordinates (x, y)")
    return point


def given_or(value: Any, default: Any) -> Any:
    """``value`` unless it was left out (None, or an empty CSV cell): a 0 is a value, and is
    checked as one."""
    return default if value is None or value == "" else value


def _check_intrinsics(path: Path, label: str, k: Intrinsics) -> None:
    from lensfit.io.limits import DISTORTION_MAX, INTRINSICS_MAX_PX

    checks = (("focal_length_px", (k.focal_length_px,), 0.0, INTRINSICS_MAX_PX, False),
              ("focal_length_sigma_px", (k.focal_length_sigma_px,), 0.0, INTRINSICS_MAX_PX, True),
              ("principal_point_px", k.principal_point_px, -INTRINSICS_MAX_PX, INTRINSICS_MAX_PX, True),
              ("distortion", k.distortion, -DISTORTION_MAX, DISTORTION_MAX, True))
    for name, values, lo, hi, closed in checks:
        try:
            ok = all((lo <= float(v) if closed else lo < float(v)) and float(v) <= hi for v in values)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise SpecError(path, f"intrinsics.{label}.{name}", f"got {list(values) if len(values) > 1 else values[0]!r}:"
                            f" finite numbers {'from' if closed else 'above'} {lo:g} to {hi:g} expected (as lensfit "
                            "measure writes them)")


@dataclass
class SampleTable:
    """Samples plus what was learnt on the way (intrinsics, poses, detections)."""

    samples: list[Sample] = field(default_factory=list)
    intrinsics: dict[str, Intrinsics] = field(default_factory=dict)
    poses: dict[tuple[str, str], TargetPose] = field(default_factory=dict)
    pixel_pitch_mm: float = float("nan")
    image_shape: tuple[int, int] = (0, 0)
    warnings: list[str] = field(default_factory=list)
    #: image file name -> (target id, detected corner positions (N, 2) px) of every target found
    #: (after refinement); kept in memory for the fit report's overlays, not written to files
    corners_px: dict[str, list[tuple[str, np.ndarray]]] = field(default_factory=dict)
    #: seconds spent per stage (read, detect, calibrate, measure) by
    #: :func:`lensfit.measurement.measure.measure`; kept in memory for ``lensfit bench-stages``, never
    #: written (files stay reproducible)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    #: per sample, the blur estimator's RMS residual in units of the noise (None where it gives
    #: none); kept in memory for the diffraction test of ``lensfit.measurement.pipeline``, never written
    fit_rms: list[float | None] = field(default_factory=list)
    #: per sample, its edge's offset toward the bright side from the line through the target's
    #: corners as found (px; None where not read); in memory for the tone test of
    #: ``lensfit.measurement.processing``, never written
    bright_offset_px: list[float | None] = field(default_factory=list)
    #: per sample, the edge geometry its blur was read with (an ``EdgeTask`` with only the edge
    #: estimator's context, ``EDGE_CONTEXT``), in memory for ``Measurement.reread`` (lensfit.measurement.measure)
    edge_tasks: list[Any] = field(default_factory=list)
    #: per sample, the lens distortion's stretch across its edge that the reading was divided by
    #: (1 where none; ``lensfit.measurement.edge_geometry.undistorted_blur``), in memory for the
    #: processing model's readings (``lensfit.measurement.processing``)
    blur_scale: list[float] = field(default_factory=list)
    #: what ``lensfit.measurement.pipeline``'s diffraction test found (None where it did not run)
    diffraction: dict[str, Any] | None = None
    #: what the stack's ``[lens]`` says (``pupil_magnification``, ``focusing``, ``ideal``,
    #: ``widest_f_number``), which the fit takes where no argument gives it; written to the samples JSON
    lens: dict[str, Any] = field(default_factory=dict)
    #: settings left out of the measurement, each with why and what would fix it (a setting whose
    #: views cannot calibrate it, in a stack whose other settings can); written to the samples
    #: JSON, and refused by name in the fit's results
    left_out_settings: dict[str, str] = field(default_factory=dict)

    COLUMNS = SAMPLES_CSV_COLUMNS

    def __len__(self) -> int:
        return len(self.samples)

    def valid(self) -> list[Sample]:
        """Samples with a measured diameter."""
        return [s for s in self.samples if s.coc_diameter_px is not None]

    def column(self, name: str) -> np.ndarray:
        return np.array([getattr(s, name) for s in self.samples])

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for s in self.samples:
            row = asdict(s)
            row["start_px"], row["end_px"] = list(s.start_px), list(s.end_px)
            row["flags"] = ";".join(s.flags)
            out.append({k: row[k] for k in self.COLUMNS})
        return out

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "samples": self.rows(),
            "pixel_pitch_mm": self.pixel_pitch_mm,
            "image_shape_px": list(self.image_shape),
            "intrinsics": {k: {**asdict(v), "principal_point_px": list(v.principal_point_px),
                               "distortion": list(v.distortion)} for k, v in self.intrinsics.items()},
            "warnings": self.warnings,
            "provenance": provenance("lensfit", dated=False),
        } | ({"lens": {k: list(v) if isinstance(v, tuple) else v for k, v in self.lens.items()}} if self.lens else {}) \
          | ({"left_out_settings": dict(self.left_out_settings)} if self.left_out_settings else {})

    @classmethod
    def read(cls, path: str | Path) -> "SampleTable":
        """A table written by :meth:`write`. JSON keeps the intrinsics and pixel pitch; a CSV
        repeats its setting's focal length in px (and 1 sigma) and the pixel pitch on every row
        (CSVs from before that hold only the samples: give the pitch and focal length to the fit)."""
        path = Path(path)
        if not path.is_file():
            raise SpecError(path, "", "no such file; write samples with lensfit measure --out")
        if path.suffix.lower() == ".csv":
            rows = read_samples_csv(path)
            doc: dict[str, Any] = {"samples": rows, **csv_calibration(path, rows)}
        else:
            from lensfit.io.specs import load_json

            doc = load_json(path)
            if not isinstance(doc, dict) or not isinstance(doc.get("samples"), list):
                raise SpecError(path, "samples", "missing: a samples JSON written by lensfit measure has a list here")
        try:
            table = cls(pixel_pitch_mm=float(doc.get("pixel_pitch_mm") or float("nan")),
                        image_shape=tuple(doc.get("image_shape_px") or (0, 0)),
                        warnings=[str(w) for w in doc.get("warnings", [])])
        except (TypeError, ValueError) as exc:
            raise SpecError(path, "pixel_pitch_mm", f"unreadable ({exc}); expected what lensfit measure writes") from None
        lens = doc.get("lens") or {}
        if not isinstance(lens, dict) or not set(lens) <= {"pupil_magnification", "focusing", "ideal",
                                                            "widest_f_number"}:
            raise SpecError(path, "lens", "holds what stack.toml's [lens] says: pupil_magnification, focusing, "
                            "ideal, widest_f_number")
        table.lens = {k: tuple(v) if isinstance(v, list) else v for k, v in lens.items()}
        left_out = doc.get("left_out_settings") or {}
        if not (isinstance(left_out, dict) and all(isinstance(v, str) for v in left_out.values())):
            raise SpecError(path, "left_out_settings", "maps setting labels to why each was left out, as lensfit "
                            "measure writes it")
        table.left_out_settings = {str(k): v for k, v in left_out.items()}
        intrinsics = doc.get("intrinsics") or {}
        if not isinstance(intrinsics, dict):
            raise SpecError(path, "intrinsics", "must map setting labels to calibrations")
        for label, v in intrinsics.items():
            try:
                table.intrinsics[label] = Intrinsics(
                    float(v["focal_length_px"]), tuple(v.get("principal_point_px", (0.0, 0.0))),
                    tuple(v.get("distortion", [0.0] * 5)), float(v.get("rms_px", 0.0)), int(v.get("views", 0)),
                    str(v.get("source", "file")), float(v.get("focal_length_sigma_px", 0.0)),
                    str(v.get("focal_length_sigma_method", "")),
                    float(v.get("focal_length_sigma_dof", 0.0)), float(v.get("informative_views", 0.0)))
            except (AttributeError, KeyError, TypeError, ValueError) as exc:
                raise SpecError(path, f"intrinsics.{label}", f"unreadable calibration ({exc!r}); expected the fields "
                                "lensfit measure writes") from None
            _check_intrinsics(path, label, table.intrinsics[label])
        for i, r in enumerate(doc["samples"]):
            if not isinstance(r, dict):
                raise SpecError(path, f"samples[{i}]", f"got {r!r}: a sample's columns by name expected (as "
                                "lensfit measure writes them)")
            try:
                table.samples.append(Sample.from_row(r))
            except InputError as exc:
                hint = f" ({exc.hint})" if exc.hint else ""
                raise SpecError(path, f"samples[{i}].{exc.argument}", f"got {exc.value!r}: {exc.requirement} "
                                f"expected, as lensfit measure writes it{hint}") from None
        return table

    def write(self, path: str | Path) -> None:
        """CSV (``.csv``) or JSON (``.json``) by suffix."""
        path = Path(path)
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps(self.to_json_dict(), indent=1, allow_nan=False))
            return
        with path.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=self.COLUMNS + SAMPLES_CSV_CALIBRATION)
            writer.writeheader()
            for row in self.rows():
                row = dict(row)
                row["start_px"] = f"{row['start_px'][0]:.3f} {row['start_px'][1]:.3f}"
                row["end_px"] = f"{row['end_px'][0]:.3f} {row['end_px'][1]:.3f}"
                k = self.intrinsics.get(row["setting"])
                pitch = self.pixel_pitch_mm if math.isfinite(self.pixel_pitch_mm) else None
                fitted = k is not None and k.source == "calibrated"  # the distortion the calibration found
                row.update(pixel_pitch_mm=None if pitch is None else repr(pitch),
                           focal_length_px=None if k is None else repr(k.focal_length_px),
                           focal_length_sigma_px=None if k is None else repr(k.focal_length_sigma_px),
                           distortion_k1=repr(float(k.distortion[0])) if fitted else None,
                           distortion_k2=repr(float(k.distortion[1])) if fitted else None)
                writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
