"""The command-line process's settings (lensfit.runtime.running.command_process), made before numpy loads."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def numpy_huge_pages(env: dict[str, str]) -> str:
    """numpy's transparent-huge-page request in a fresh process set up as ``lensfit`` sets up its own."""
    code = ("from lensfit.runtime.running import command_process; command_process(); import numpy; "
            "from numpy._core import multiarray as m; print(m._get_madvise_hugepage())")
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_the_command_process_asks_numpy_for_no_huge_pages_unless_the_user_says():
    pytest.importorskip("numpy._core.multiarray")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    assert numpy_huge_pages(env) == "False"
    assert numpy_huge_pages({**env, "NUMPY_MADVISE_HUGEPAGE": "1"}) == "True"  # a user's own setting stands
