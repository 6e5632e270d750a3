"""The library keeps JAX's compiled functions as the programs do (``import lensfit`` switches the
persistent cache on), and leaves alone a program that set JAX's cache itself or said off.

Each case runs in a fresh interpreter: the switch happens at import."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PROBE = ("import json, os, lensfit, lensfit.runtime.jaxcache as jaxcache\n"
         "print(json.dumps({'jax_dir': os.environ.get('JAX_COMPILATION_CACHE_DIR'),"
         " 'store': None if jaxcache._DIR[0] is None else str(jaxcache._DIR[0])}))\n")


def probe(env: dict[str, str]) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in ("LENSFIT_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR")}
    run = subprocess.run([sys.executable, "-c", PROBE], env={**clean, **env}, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_import_switches_the_cache_on(tmp_path):
    got = probe({"LENSFIT_JAX_CACHE": str(tmp_path / "cache")})
    assert got == {"jax_dir": str(tmp_path / "cache"), "store": str(tmp_path / "cache" / "traces")}
    assert (tmp_path / "cache" / "traces").is_dir()


def test_a_child_of_a_lensfit_process_keeps_the_cache(tmp_path):
    # the parent's setting, inherited through the environment, is lensfit's own: the child's
    # compiled traces must be found (without them a script re-traced every solver: 4x the CLI's time)
    ours = str(tmp_path / "cache")
    got = probe({"LENSFIT_JAX_CACHE": ours, "JAX_COMPILATION_CACHE_DIR": ours})
    assert got["store"] == str(tmp_path / "cache" / "traces")


@pytest.mark.parametrize("env", [{"LENSFIT_JAX_CACHE": "off"}, {"JAX_COMPILATION_CACHE_DIR": "/nonexistent/mine"}],
                         ids=["off", "the program's own folder"])
def test_the_cache_is_left_alone(env, tmp_path):
    got = probe({"HOME": str(tmp_path), **env})
    assert got["store"] is None
    assert got["jax_dir"] == env.get("JAX_COMPILATION_CACHE_DIR")
    assert not (tmp_path / ".cache" / "lensfit").exists()
