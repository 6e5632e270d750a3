"""Running a command: stop signals as exceptions, and every failure as one line with an exit
status (``run_guarded``), for both programs' command lines. Outputs in flight are left whole or
not at all (``lensfit.outputs.writers``)."""

from __future__ import annotations

import contextlib
import errno
import os
from typing import Callable, Iterator

from lensfit.errors import Interrupted, OutputError


_RECEIVED: list[int] = []


def check_interrupted() -> None:
    """Raise :class:`Interrupted` if a stop signal arrived (even one whose exception was
    swallowed by a C callback); writers call it before putting anything in place."""
    if _RECEIVED:
        import signal

        if _RECEIVED[-1] == signal.SIGINT:
            raise KeyboardInterrupt
        raise Interrupted(_RECEIVED[-1])


@contextlib.contextmanager
def signals_as_exceptions() -> Iterator[None]:
    """Turn SIGTERM (and SIGHUP) into :class:`lensfit.errors.Interrupted` inside the block, so
    that the ``finally`` clauses of the writers run and remove their temporary files and locks;
    Ctrl-C (SIGINT) stays a KeyboardInterrupt but is recorded, so that one a C callback swallowed
    still stops the command (:func:`check_interrupted`)."""
    import signal

    def handler(signum, frame):
        _RECEIVED.append(signum)  # kept: a raise inside a C callback (e.g. JAX's gc hook) is swallowed
        raise Interrupted(signum)

    def interrupt(signum, frame):
        # Ctrl-C stays a KeyboardInterrupt, but is kept too: raised inside a C callback it is
        # swallowed, and the command would finish and write as if never interrupted (seen: exit 0).
        _RECEIVED.append(signum)
        raise KeyboardInterrupt

    previous = {}
    handlers = [(signal.SIGTERM, handler), (getattr(signal, "SIGHUP", None), handler)]
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        handlers.append((signal.SIGINT, interrupt))
    for sig, fn in handlers:
        if sig is None:
            continue
        try:
            previous[sig] = signal.signal(sig, fn)
        except ValueError:  # not the main thread
            pass
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def run_guarded(prog: str, body: Callable[[], int],
                known: Callable[[Exception], tuple[str, int] | None] = lambda exc: None) -> int:
    """Run a CLI command: every failure becomes one line on stderr and a non-zero exit status.

    ``known`` maps the command's own exceptions to (message, status). Then: Ctrl-C -> 130,
    SIGTERM -> 143 (SIGHUP 129), with the writers' temporary files and locks already removed;
    :class:`OutputError` / :class:`SpecError` / :class:`InputError` -> 2; out of memory -> 1;
    an operating-system error -> 1 naming the file; anything unforeseen -> 70 with its type and
    message (set ``LENSFIT_TRACEBACK=1`` to see the traceback).
    """
    import sys

    from lensfit.errors import InputError, SpecError

    interrupted = False
    try:
        with signals_as_exceptions():
            code = body()
            check_interrupted()
            return code
    except Interrupted as exc:
        message, code, interrupted = (f"{exc}; temporary files removed, existing outputs unchanged", exc.exit_code,
                                      True)
    except KeyboardInterrupt:
        message, code, interrupted = ("interrupted (Ctrl-C); temporary files removed, existing outputs unchanged",
                                      130, True)
    except Exception as exc:  # noqa: BLE001 - the one place where every failure becomes a message
        mapped = known(exc)
        if mapped is not None:
            message, code = mapped
        elif isinstance(exc, (OutputError, SpecError, InputError)):
            message, code = str(exc), 2
        elif isinstance(exc, MemoryError):
            message, code = ("out of memory; use smaller or fewer images (see --max-megapixels) or a machine "
                             "with more memory"), 1
        elif isinstance(exc, OSError):
            where = f"{exc.filename}: " if exc.filename else ""
            message, code = f"{where}{exc.strerror or exc}", 1
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                message += ("; free some space on the output's disk or write elsewhere (--out): the outputs are "
                            "written whole or not at all, and nothing was left half-written")
        else:
            if os.environ.get("LENSFIT_TRACEBACK"):
                raise
            message, code = (f"internal error ({type(exc).__name__}: {exc}); please report it with the command "
                             "line (LENSFIT_TRACEBACK=1 shows the traceback)"), 70
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr)
    if interrupted:
        # Interrupted: the writers have already removed their temporary files and locks. Skip
        # the interpreter's teardown, which can run beside an XLA computation still finishing on
        # its own threads and crash there (seen: SIGSEGV instead of the exit status).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


#: The command-line process's BLAS libraries (numpy's and SciPy's OpenBLAS) run one thread
#: unless the environment says otherwise. The work hands them small matrices, from two threads of
#: its own (the measuring and the loading of compiled code, lensfit.measurement.measure); their worker pools
#: spun between calls: 0.8 of 4.3 s of CPU in a fresh `lensfit fit out/demo` on 2 cores, wall
#: 2.52 -> 2.30 s (five runs each). Read by OpenBLAS when it loads, so set before numpy is imported.
BLAS_THREADS = {"OPENBLAS_NUM_THREADS": "1"}
#: numpy asks the kernel for transparent huge pages on every large array (madvise); where the
#: kernel's defrag policy honours that request at once (Linux's usual "madvise"), each fresh
#: image-sized array can stall on memory compaction as its pages fault in. A 12-shot 24 MP
#: stack (`lensfit fit --jobs 2`, 2 cores, three runs each way): 13.5 -> 10.7 s wall, the
#: kernel's CPU 8.5 -> 2.5 s, results identical. Read by numpy when it loads.
NUMPY_ENV = {"NUMPY_MADVISE_HUGEPAGE": "0"}


def command_process() -> None:
    """Settings of a ``lensfit`` command-line process, made before anything heavy is imported:
    :data:`BLAS_THREADS` and :data:`NUMPY_ENV` where the environment sets none (a user's own
    setting stands; child processes inherit them), and glibc's reuse of freed memory
    (:func:`_keep_freed_memory`).
    Called by the ``lensfit`` program and in the benchmark's own worker processes
    (``lensfit.bench.runs``); importing the library changes nothing in the caller's process."""
    for name, value in {**BLAS_THREADS, **NUMPY_ENV}.items():
        os.environ.setdefault(name, value)
    _keep_freed_memory()


#: glibc's malloc: blocks under MMAP_THRESHOLD_BYTES come from the heap, which keeps up to
#: TRIM_THRESHOLD_BYTES of freed memory for reuse. By default a block over 128 kB to 32 MB (the
#: threshold adapts) is mapped afresh and unmapped when freed, so each new image-sized array
#: (8 MB at 1 MP in float64) faulted in zeroed pages again: 7 % of a `lensfit fit out/demo`'s
#: CPU was the kernel clearing pages (0.18 s of CPU, 0.09 s of wall, eight runs each way).
MMAP_THRESHOLD_BYTES = 64 << 20
TRIM_THRESHOLD_BYTES = 256 << 20


def _keep_freed_memory() -> None:
    """Set :data:`MMAP_THRESHOLD_BYTES` and :data:`TRIM_THRESHOLD_BYTES` where the C library is
    glibc (``mallopt``) and the environment does not set them itself; elsewhere nothing."""
    if any(k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")):
        return
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    mallopt(m_mmap_threshold, MMAP_THRESHOLD_BYTES)
    mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES)


def exit_process(code: int) -> None:
    """End a command-line process with ``code``. Where JAX was loaded, its exit handlers (which
    tear down the compiled code and the backends: 0.2-0.3 s of a process that fits a stack in 4)
    are skipped with ``os._exit``, once the standard streams are flushed and only where nothing
    else is left running (no other thread, no child process): every output is written and
    closed by then, and the temporary folders are context-managed. Otherwise ``sys.exit``."""
    import sys
    import threading

    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed pipe: the plain exit reports it as Python would
        sys.exit(code)
    children = "multiprocessing" in sys.modules and sys.modules["multiprocessing"].active_children()
    if "jax" in sys.modules and threading.active_count() == 1 and not children:
        os._exit(code)
    sys.exit(code)
