"""The library against the command line on the same job (``lensfit bench-api``).

The README's Python example fits a stack with :func:`lensfit.measurement.pipeline.measure_and_fit`, as
``lensfit fit`` does. Each is run as a fresh process, the way a user runs a script or a command:
import, JAX's start, loading the compiled functions from the persistent cache, reading,
detecting, calibrating, measuring and fitting. One warm-up run of each fills the cache; then
``pairs`` pairs run back to back, alternating which goes first, so that a drifting machine
weighs on both alike. The figure is the median of the pairs' ratios.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

#: The README's fit, as a script's process runs it.
API_SCRIPT = ("import sys\n"
              "from lensfit.measurement.pipeline import measure_and_fit\n"
              "samples, result, rounds = measure_and_fit(sys.argv[1], auto_diffraction=True)\n"
              "print(result.code)\n")


def _seconds(command: list[str]) -> float:
    start = time.perf_counter()
    run = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - start
    if run.returncode not in (0, 3):  # 3: a fit that refuses a quantity still ran the whole job
        raise RuntimeError(f"{' '.join(command[:4])} ... exited {run.returncode}: {run.stderr.strip()[-300:]}")
    return seconds


def run(stack: str | Path, pairs: int = 3, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Seconds of a fresh ``lensfit fit STACK`` process and of a fresh process running
    :data:`API_SCRIPT` on the same stack; their medians and the median of the pairs' ratios."""
    stack = str(stack)
    with tempfile.TemporaryDirectory(prefix="lensfit-bench-api-") as tmp:
        cli = [sys.executable, "-m", "lensfit", "fit", stack, "--out", str(Path(tmp) / "results.json"), "--force"]
        api = [sys.executable, "-c", API_SCRIPT, stack]
        if progress:
            progress("warm-up (fills the compilation cache)")
        _seconds(cli)
        _seconds(api)
        times: dict[str, list[float]] = {"cli": [], "api": []}
        for k in range(pairs):
            if progress:
                progress(f"pair {k + 1} of {pairs}")
            order = (("cli", cli), ("api", api)) if k % 2 == 0 else (("api", api), ("cli", cli))
            for name, command in order:
                times[name].append(_seconds(command))
    ratios = [a / c for a, c in zip(times["api"], times["cli"])]
    from lensfit.outputs.writers import provenance

    return {"benchmark": "api_vs_cli", "stack": stack, "pairs": pairs,
            "seconds_cli": times["cli"], "seconds_api": times["api"],
            "median_seconds_cli": statistics.median(times["cli"]),
            "median_seconds_api": statistics.median(times["api"]),
            "median_ratio": statistics.median(ratios),
            "provenance": provenance("lensfit", ["lensfit", "bench-api", stack, "--pairs", str(pairs)])}


def markdown(record: dict[str, Any]) -> str:
    """The validation page's section for a record of :func:`run`."""
    prov = record.get("provenance", {})
    return "\n".join([
        "## The library against the command line", "",
        f"Fresh processes on `{record['stack']}`, {record['pairs']} alternating pairs after a warm-up; measured "
        f"{(prov.get('date') or '')[:10]} with `{prov.get('command')}`.", "",
        "| process | median seconds |", "|---|---|",
        f"| `lensfit fit` | {record['median_seconds_cli']:.2f} |",
        f"| the README's `measure_and_fit` in a script | {record['median_seconds_api']:.2f} |",
        f"| ratio (median of the pairs') | {record['median_ratio']:.2f}x |"])
