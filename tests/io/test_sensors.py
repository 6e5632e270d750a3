"""Sensor-format data and the schema validation that guards it."""

from __future__ import annotations

import pytest

from lensfit import optics
from lensfit.errors import InputError, SpecError
from lensfit.io.sensors import sensor_format, sensor_formats
from lensfit.io.specs import load_toml, validate


def test_course_chart_crop_factors():
    # The course's chart prints a crop factor for each format; the diagonal ratio to 36 x 24
    # must reproduce it (the chart rounds, and lists full frame as 35 x 24: 2% tolerance).
    charted = [f for f in sensor_formats().values() if f.chart_crop_factor is not None]
    assert len(charted) == 6
    for fmt in charted:
        assert float(optics.crop_factor(fmt.width_mm, fmt.height_mm)) == pytest.approx(fmt.chart_crop_factor, rel=0.02)


def test_lookup_by_alias_and_pitch():
    assert sensor_format("35mm").name == "full-frame"
    assert sensor_format("APS-C").name == "aps-c"
    assert sensor_format("full-frame-24mp").pixel_pitch_mm == pytest.approx(0.006)
    assert sensor_format("full-frame").pixel_pitch_mm is None


def test_unknown_lists_valid_names():
    with pytest.raises(InputError) as info:
        sensor_format("potato")
    assert "potato" in str(info.value) and "full-frame" in str(info.value)


def test_bad_file_names_file_field_and_value(tmp_path):
    bad = tmp_path / "formats.toml"
    bad.write_text('[[format]]\nname = "x"\nwidth_mm = -3\nheight_mm = 2\n')
    with pytest.raises(SpecError) as info:
        validate(load_toml(bad), "sensor_formats", bad)
    msg = str(info.value)
    assert str(bad) in msg and "format[0].width_mm" in msg and "-3" in msg
    missing = tmp_path / "missing.toml"
    missing.write_text('[[format]]\nname = "x"\nwidth_mm = 3\n')
    with pytest.raises(SpecError, match=r"format\[0\]\.height_mm: is required"):
        validate(load_toml(missing), "sensor_formats", missing)
    broken = tmp_path / "broken.toml"
    broken.write_text("[[format]\n")
    with pytest.raises(SpecError, match="not valid TOML"):
        load_toml(broken)
