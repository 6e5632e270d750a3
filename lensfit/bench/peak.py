"""A command's own peak memory: run it from a small launcher interpreter and read the peak
resident set from ``wait4``. (Linux counts in a process's peak the memory of the process it was
forked from: started straight from a pytest, a benchmark driver or a notebook of a gigabyte,
the figure would be theirs.)"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass

#: Runs a command, its standard output discarded, and writes its exit status, peak resident
#: memory (kB) and CPU seconds (user and system) as JSON.
_LAUNCHER = """
import json, os, signal, subprocess, sys, time
proc = subprocess.Popen(sys.argv[2:], stdout=subprocess.DEVNULL, start_new_session=True)
deadline = time.monotonic() + float(sys.argv[1])
while True:
    pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
    if pid:
        break
    if time.monotonic() > deadline:
        os.killpg(proc.pid, signal.SIGKILL)
        pid, status, usage = os.wait4(proc.pid, 0)
        break
    time.sleep(0.02)
proc.returncode = 0
print(json.dumps([os.waitstatus_to_exitcode(status), usage.ru_maxrss, usage.ru_utime + usage.ru_stime]))
"""


@dataclass(frozen=True)
class Peak:
    """How a command ended: exit status (None where the launcher said nothing), seconds, peak
    resident memory in bytes, what it wrote to standard error, and the CPU seconds it used (user
    and system, every thread: over ``seconds``, how many cores it kept busy)."""

    status: int | None
    seconds: float
    peak_bytes: int
    stderr: str
    cpu_seconds: float = 0.0


def run_with_peak(argv: list[str], timeout_s: float) -> Peak:
    """Run ``argv`` (killed with its process group after ``timeout_s``) and measure it."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _LAUNCHER, str(timeout_s), *argv], capture_output=True, text=True,
                          errors="replace")
    seconds = time.perf_counter() - start
    try:
        status, peak_kb, cpu = json.loads(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        status, peak_kb, cpu = None, 0, 0.0
    return Peak(status, seconds, int(peak_kb) * 1024, done.stderr, float(cpu))  # (ru_maxrss: kilobytes on Linux)
