"""Fixtures shared by the test modules: stacks rendered once per session."""

from __future__ import annotations

import os

# JAX's strict dtype promotion for everything the tests run (subprocesses too): an int array
# meeting a float one is an error, not a silent promotion, so that the float64 fit stays float64.
os.environ.setdefault("JAX_NUMPY_DTYPE_PROMOTION", "strict")

import pytest  # noqa: E402
from hypothesis import settings

# Property tests draw the same examples on every run (the repository's rule: deterministic given
# a seed); a failure found once stays reproducible instead of appearing at random in CI.
settings.register_profile("deterministic", derandomize=True)
settings.load_profile("deterministic")

from synth.rendering import render
from synth.scene import scene_from_dict
from synth.stack import write_stack


@pytest.fixture(scope="session")
def camera_raw_stack(tmp_path_factory):
    """data_specs/scenes/camera_raw.toml rendered (Bayer DNGs at f/11 with noise and
    diffraction); read only by the tests that take it."""
    from lensfit.io.specs import specs_dir
    from synth.scene import load_scene

    out = tmp_path_factory.mktemp("camera-raw") / "dng"
    write_stack(render(load_scene(specs_dir() / "scenes" / "camera_raw.toml")), out)
    return out


@pytest.fixture(scope="session")
def calibration_stack(tmp_path_factory):
    """A small ChArUco stack (8 shots, some tilted) rendered by synth."""
    from helpers import calibration_scene

    scene = scene_from_dict(calibration_scene())
    out = tmp_path_factory.mktemp("stack") / "calib"
    write_stack(render(scene), out)
    return out


@pytest.fixture(scope="session")
def calibration_samples(calibration_stack):
    """The calibration stack measured with the edge estimator (shared: measuring takes seconds)."""
    from lensfit.measurement.measure import measure

    return measure(calibration_stack)
