"""The sample table's flags are typed from the estimator to the files and back: members of
lensfit.estimators.base.Flag in memory, their names in the CSV and JSON files, and a name the
program does not write is refused with the sample and the name."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest

from lensfit.errors import SpecError
from lensfit.estimators.base import Flag
from lensfit.io.samples import SampleTable

ROOT = Path(__file__).resolve().parents[2]


def test_flags_are_members_and_survive_the_files(calibration_samples, tmp_path):
    flagged = [s for s in calibration_samples.samples if s.flags]
    assert flagged, "the calibration stack has flagged edges (its tilted boards' axis-aligned ones at least)"
    assert all(isinstance(f, Flag) for s in calibration_samples.samples for f in s.flags)
    for suffix in ("csv", "json"):
        path = tmp_path / f"samples.{suffix}"
        calibration_samples.write(path)
        back = SampleTable.read(path)
        assert [s.flags for s in back.samples] == [s.flags for s in calibration_samples.samples]
        assert all(isinstance(f, Flag) for s in back.samples for f in s.flags)
    with (tmp_path / "samples.csv").open() as fh:  # the file holds the names, ";"-separated
        cells = [row["flags"] for row in csv.DictReader(fh)]
    assert cells == [";".join(f.value for f in s.flags) for s in calibration_samples.samples]


def test_a_flag_lensfit_does_not_write_is_refused_naming_it(calibration_samples, tmp_path):
    path = tmp_path / "samples.csv"
    calibration_samples.write(path)
    text = path.read_text().splitlines()
    header = next(csv.reader([text[0]]))
    row = next(csv.reader([text[1]]))
    row[header.index("flags")] = "axis_aligned;sharpened_by_hand"
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows([header, row])
    with pytest.raises(SpecError) as err:
        SampleTable.read(path)
    assert "samples[0]" in str(err.value) and "sharpened_by_hand" in str(err.value)


def test_every_flag_the_guide_names_is_one_the_program_writes():
    guide = (ROOT / "docs" / "src" / "guides" / "measure.md").read_text()
    section = guide.split("## Flags", 1)[1].split("\n## ", 1)[0]
    named = set(re.findall(r"`([a-z_]+)`", section)) - {"lensfit"}
    assert named and named <= {f.value for f in Flag}, named - {f.value for f in Flag}
