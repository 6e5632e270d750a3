"""`lensfit dof` against the course formulas, computed here by hand in plain Python."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest

from lensfit.cli import main


def run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def course(f, N, C, D):
    """The course's DOF formulas (CS184 notes), written out independently of lensfit."""
    near = D * f**2 / (f**2 + N * C * (D - f))
    den = f**2 - N * C * (D - f)
    far = D * f**2 / den if den > 0 else math.inf
    return near, far, f**2 / (N * C) + f


def test_issue_example_agrees_with_course(capsys):
    code, out, _ = run(capsys, "dof", "--focal-length", "50", "--f-number", "8", "--focus-distance", "3000",
                       "--coc", "0.03", "--json")
    assert code == 0
    data = json.loads(out)
    near, far, H = course(50, 8, 0.03, 3000)
    assert data["near_limit_mm"] == pytest.approx(near, rel=1e-12)
    assert data["far_limit_mm"] == pytest.approx(far, rel=1e-12)
    assert data["depth_of_field_mm"] == pytest.approx(far - near, rel=1e-12)
    assert data["hyperfocal_distance_mm"] == pytest.approx(H, rel=1e-12)
    assert data["depth_of_field_approx_mm"] == pytest.approx(2 * 8 * 0.03 * 3000**2 / 50**2, rel=1e-12)


def test_beyond_hyperfocal_gives_null_far_limit(capsys):
    code, out, _ = run(capsys, "dof", "--focal-length", "24", "--f-number", "11", "--focus-distance", "5000",
                       "--coc", "0.03", "--json")
    data = json.loads(out)
    assert code == 0 and data["far_limit_mm"] is None and data["depth_of_field_mm"] is None
    near, far, H = course(24, 11, 0.03, 5000)
    assert math.isinf(far) and data["near_limit_mm"] == pytest.approx(near, rel=1e-12)


def test_sensor_default_coc_and_pixels(capsys):
    code, out, _ = run(capsys, "dof", "--focal-length", "50", "--f-number", "2.8", "--focus-distance", "2000",
                       "--sensor", "full-frame-24mp", "--json")
    data = json.loads(out)
    coc = math.hypot(36, 24) / 1500
    assert code == 0
    assert data["acceptable_coc_diameter_mm"] == pytest.approx(coc, rel=1e-12)
    assert data["acceptable_coc_diameter_px"] == pytest.approx(coc / 0.006, rel=1e-12)
    assert data["near_limit_mm"] == pytest.approx(course(50, 2.8, coc, 2000)[0], rel=1e-12)


def test_table_output_is_readable(capsys):
    code, out, _ = run(capsys, "dof", "--focal-length", "50", "--f-number", "2.8", "--focus-distance", "2000",
                       "--sensor", "aps-c", "--pixel-pitch", "0.004")
    assert code == 0
    for words in ("near limit", "far limit", "hyperfocal", "µm", "px"):
        assert words in out


@pytest.mark.parametrize(
    "argv, option, value",
    [
        (["--focal-length", "-2", "--f-number", "8", "--focus-distance", "3000", "--coc", "0.03"], "--focal-length", "-2"),
        (["--focal-length", "50", "--f-number", "0", "--focus-distance", "3000", "--coc", "0.03"], "--f-number", "0"),
        (["--focal-length", "50", "--f-number", "8", "--focus-distance", "40", "--coc", "0.03"], "--focus-distance", "40"),
        (["--focal-length", "50", "--f-number", "8", "--focus-distance", "3000", "--coc", "-0.03"], "--coc", "-0.03"),
        (["--focal-length", "50", "--f-number", "8", "--focus-distance", "3000", "--sensor", "potato"], "--sensor",
         "potato"),
        (["--focal-length", "50", "--f-number", "nan", "--focus-distance", "3000", "--coc", "0.03"], "--f-number",
         "nan"),
    ],
)
def test_invalid_input_one_line_naming_option_and_value(capsys, argv, option, value):
    code, out, err = run(capsys, "dof", *argv)
    assert code != 0
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert option in lines[0] and value in lines[0] and "must be" in lines[0]


def test_help_does_not_import_jax():
    code = ("import sys\nfrom lensfit.cli import main\ntry:\n    main(['dof', '--help'])\n"
            "except SystemExit:\n    pass\nassert 'jax' not in sys.modules, 'jax imported for --help'\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "--focal-length" in proc.stdout


_PROCESS_PROBE = """
import ctypes, os, platform
from lensfit.runtime.running import command_process
command_process()
import numpy as np

class MallInfo2(ctypes.Structure):
    _fields_ = [(k, ctypes.c_size_t) for k in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]

mapped = None
if platform.libc_ver()[0] == "glibc":
    info = ctypes.CDLL(None).mallinfo2
    info.restype = MallInfo2
    before = info().hblks
    block = np.ones(2_000_000)  # 16 MB: glibc maps a block this size afresh by default
    mapped = info().hblks - before
print(os.environ.get("OPENBLAS_NUM_THREADS"), mapped)
"""


@pytest.mark.parametrize("preset", [None, "3"])
def test_a_command_process_runs_one_blas_thread_and_reuses_freed_memory(preset):
    """lensfit.runtime.running.command_process: numpy's BLAS pool left at one thread unless the user set
    it; image-sized arrays taken from the heap instead of mapped afresh (glibc)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MALLOC_MMAP_THRESHOLD_",
                                                             "MALLOC_TRIM_THRESHOLD_")}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    proc = subprocess.run([sys.executable, "-c", _PROCESS_PROBE], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    threads, mapped = proc.stdout.split()
    assert threads == (preset or "1")
    assert mapped in ("0", "None")
    # and the probe can fail: without command_process the block is mapped
    bare = subprocess.run([sys.executable, "-c", _PROCESS_PROBE.replace("command_process()", "")],
                          capture_output=True, text=True, env=env)
    assert bare.stdout.split()[1] in ("1", "None")


@pytest.mark.parametrize("coc, says", [("30", "30 um is --coc 0.03"), ("1.5", "at most 1 mm")])
def test_a_coc_in_the_wrong_unit_is_refused_with_the_fix(capsys, coc, says):
    """Micrometres typed for millimetres (30 for 0.03) give a depth of field off by 1000x: refused,
    naming the likely slip; 0.2 mm (large format) is still taken."""
    code, _, err = run(capsys, "dof", "--focal-length", "50", "--f-number", "4", "--focus-distance", "2000",
                       "--coc", coc)
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1
    assert run(capsys, "dof", "--focal-length", "150", "--f-number", "16", "--focus-distance", "5000",
               "--coc", "0.2")[0] == 0
