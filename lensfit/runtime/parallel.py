"""Per-image work in threads, results in the images' order.

Decoding an image and OpenCV's detection release the GIL, so images run side by side in threads
of one process (no second JAX start-up, no pickling of images). At most ``jobs`` items are in
flight, so memory holds a few images, not the stack; results come back in the items' order, so
they are the same whatever ``jobs`` is. An exception is raised where its item's result is taken
(the first failing item in order), after the items in flight have ended.
"""

from __future__ import annotations

import os
from collections import deque
from typing import Callable, Iterable, Iterator, TypeVar

from lensfit.errors import InputError

#: The most threads ``jobs`` may ask for.
MAX_JOBS = 256

T = TypeVar("T")
R = TypeVar("R")


def default_jobs() -> int:
    """The cores this process may use (its CPU affinity where the system says it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def check_jobs(jobs: int | None) -> int:
    """``jobs`` as a count of threads (None: :func:`default_jobs`)."""
    if jobs is None:
        return default_jobs()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or not 1 <= jobs <= MAX_JOBS:
        raise InputError("jobs", jobs, f"a whole number from 1 to {MAX_JOBS}",
                         "the images processed at once, e.g. the cores")
    return jobs


def in_threads(fn: Callable[[T], R], items: Iterable[T], jobs: int | None = None) -> Iterator[R]:
    """``fn(item)`` for every item, at most ``jobs`` at once, yielded in the items' order."""
    jobs = check_jobs(jobs)
    items = list(items)
    if jobs == 1 or len(items) <= 1:
        yield from map(fn, items)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="lensfit-image") as pool:
        flight: deque = deque()
        todo = iter(items)
        try:
            for item in todo:
                flight.append(pool.submit(fn, item))
                if len(flight) >= jobs:
                    yield flight.popleft().result()
            while flight:
                yield flight.popleft().result()
        finally:
            for future in flight:
                future.cancel()
