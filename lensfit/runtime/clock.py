"""Seconds per stage of a measuring run (``lensfit.measurement.measure``), reading apart."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from typing import Callable

import numpy as np


class StageClock:
    """Seconds per stage; reading images (which happens inside other stages) counted apart.

    A read on the thread that runs a stage is taken out of that stage and counted as ``read``.
    A read on another thread (the next image read ahead while this one's edges are measured)
    overlaps the stage: it is counted in ``read_overlapped``, not a stage of its own, and the
    stage keeps the time it waited for it. The stages then add up to the wall time."""

    def __init__(self):
        self.seconds = {"read": 0.0, "detect": 0.0, "calibrate": 0.0, "measure": 0.0, "read_overlapped": 0.0}
        self._owner = threading.get_ident()

    def reader(self, read: Callable[[int], np.ndarray]) -> Callable[[int], np.ndarray]:
        def timed(i: int) -> np.ndarray:
            t = time.perf_counter()
            try:
                return read(i)
            finally:
                key = "read" if threading.get_ident() == self._owner else "read_overlapped"
                self.seconds[key] += time.perf_counter() - t
        return timed

    @contextmanager
    def stage(self, name: str):
        t, r = time.perf_counter(), self.seconds["read"]
        try:
            yield
        finally:
            self.seconds[name] += (time.perf_counter() - t) - (self.seconds["read"] - r)

    @contextmanager
    def parallel(self, names: tuple[str, ...]):
        """Stages run side by side in threads: the caller reports each item's seconds per stage
        (in ``names``' order) to the function this yields, and the section's wall time is shared
        among the stages in proportion to those sums."""
        sums = [0.0] * len(names)

        def spent(*seconds: float) -> None:
            for k, v in enumerate(seconds):
                sums[k] += v

        t = time.perf_counter()
        try:
            yield spent
        finally:
            wall, total = time.perf_counter() - t, sum(sums)
            for name, v in zip(names, sums):
                self.seconds[name] += wall * (v / total if total > 0 else 1.0 / len(names))

