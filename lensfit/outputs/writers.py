"""Writing outputs safely: what may be replaced, one writer at a time, all or nothing.

Shared by ``lensfit`` and ``synth`` (the one atomic writer of both programs).

Rules
-----
- **Only our own outputs are replaced.** An existing output is replaced only with ``force=True``
  *and* only when :func:`written_by` recognises it as written by lensfit or synth:

  ========================  =====================================================================
  output                    recognised by
  ========================  =====================================================================
  results / samples JSON    ``provenance.program`` (or an older ``provenance.command``) naming
                            ``lensfit`` or ``synth``
  samples CSV               the exact header line ``lensfit measure`` writes
  plot / preview PNG        the PNG text chunk ``Software`` = ``lensfit ...`` or ``synth ...``
  plot SVG / PDF            the creator field the plot writer sets (``lensfit ...``)
  stack.toml (drafted)      its first line ``# Written by lensfit init`` (or ``# Written by synth``)
  HTML report               ``<meta name="generator" content="lensfit ...">`` in its head
  stack folder              its ``stack.toml`` written by synth and a ``truth.json`` that lists
                            every file the folder holds (anything else in it: refused)
  ========================  =====================================================================

  Anything else (a user's file, a folder with a user's files) is never replaced or deleted.
- **One writer per output.** :class:`OutputLock` creates ``.NAME.lock`` beside each output
  atomically (``O_CREAT | O_EXCL``) before the work starts; a second run on the same output
  fails at once with :class:`OutputError` naming the path and the first run's process id, and
  the first run's output stays intact. A lock left by a process that no longer runs (same
  host) is stale and taken over.
- **All or nothing.** :func:`write_all` writes every file to a unique temporary sibling and
  renames them into place only when all were written; without ``force`` the final step is an
  atomic create (``os.link``) that never overwrites a file another process put there.
  :func:`write_folder` does the same for a folder (a stack): a temporary sibling folder,
  swapped in at the end.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import socket
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from lensfit.errors import OutputError
from lensfit.io.specs import MAX_JSON_BYTES
from lensfit.io.samples_csv import (SAMPLES_CSV_CALIBRATION, SAMPLES_CSV_CALIBRATION_EARLIER, SAMPLES_CSV_COLUMNS,
                                    SAMPLES_CSV_EARLIER)

PROGRAMS = ("lensfit", "synth")


_SNIFF_BYTES = 1 << 16


def software_tag(program: str) -> str:
    """``"lensfit 0.1.0"``: the creator string written into plots and previews."""
    from lensfit import __version__

    return f"{program} {__version__}"


def provenance(program: str, command: Iterable[str] | None = None, *, dated: bool = True,
               **extra: Any) -> dict[str, Any]:
    """Who wrote a file and how: the one provenance record of both programs (results, samples,
    benchmark reports, truth.json). ``dated=False`` leaves out the date and the machine, for
    files that must be identical run to run given a seed (a rendered stack's truth)."""
    import datetime
    import platform

    from lensfit import __version__

    out: dict[str, Any] = {"program": program, "version": __version__}
    if command is not None:
        out["command"] = " ".join(command) if not isinstance(command, str) else command
    if dated:
        out.update(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                   python=platform.python_version(), machine=platform.machine())
    out.update(extra)
    return out


def _program_of(text: str | None) -> str | None:
    if not isinstance(text, str):
        return None
    head = text.strip().split(" ", 1)[0]
    return head if head in PROGRAMS else None


def written_by(path: str | Path) -> str | None:
    """``"lensfit"`` or ``"synth"`` if that program wrote ``path`` (file or stack folder), else None.

    Only reads: at most the first 64 KiB of a file (a PDF's last 64 KiB too), a folder's listing
    and its stack.toml / truth.json.
    """
    path = Path(path)
    try:
        if path.is_symlink():
            return None  # a link may point at anything; never replace through one
        if path.is_dir():
            return "synth" if foreign_entry(path) is None else None
        if not path.is_file():
            return None
        suffix = path.suffix.lower()
        with path.open("rb") as fh:
            head = fh.read(_SNIFF_BYTES)
            if suffix == ".pdf":
                fh.seek(max(0, path.stat().st_size - _SNIFF_BYTES))
                tail = fh.read(_SNIFF_BYTES)
    except OSError:
        return None
    if suffix == ".json":
        try:
            # (lensfit's JSON outputs are some MB at most: a larger file is not read to find out)
            doc = json.loads(path.read_text()) if path.stat().st_size <= MAX_JSON_BYTES else None
        except (OSError, ValueError, RecursionError):
            return None
        prov = doc.get("provenance") if isinstance(doc, dict) else None
        if not isinstance(prov, dict):
            return None
        return _program_of(prov.get("program")) or _program_of(prov.get("command"))
    if suffix == ".csv":
        first = head.split(b"\n", 1)[0].decode("utf-8", "replace").strip()
        header = next(csv.reader([first]), None)
        known = [list(cols + cal) for cols in (SAMPLES_CSV_COLUMNS, *SAMPLES_CSV_EARLIER)
                 for cal in ((), SAMPLES_CSV_CALIBRATION, SAMPLES_CSV_CALIBRATION_EARLIER)]
        return "lensfit" if header in known else None
    if suffix == ".png":
        return _png_software(head)
    if suffix == ".toml":  # a stack.toml drafted by lensfit init, or written by synth
        first = head.split(b"\n", 1)[0].decode("utf-8", "replace")
        for program in PROGRAMS:
            if first.startswith(f"# Written by {program} "):
                return program
        return None
    if suffix in (".html", ".htm"):
        for program in PROGRAMS:
            if f'<meta name="generator" content="{program} '.encode() in head:
                return program
        return None
    if suffix == ".svg":
        for program in PROGRAMS:
            if f"<dc:title>{program} ".encode() in head:
                return program
        return None
    if suffix == ".pdf":
        for program in PROGRAMS:
            # Plain (matplotlib) or UTF-16 with a byte-order mark (Pillow)
            for tag in (f"/Creator ({program} ".encode(), b"/Creator (\xfe\xff" + f"{program} ".encode("utf-16-be")):
                if tag in tail or tag in head:
                    return program
        return None
    return None


def _png_software(head: bytes) -> str | None:
    """The ``Software`` tEXt chunk of a PNG (chunks before the image data are in the head)."""
    if not head.startswith(b"\x89PNG\r\n\x1a\n"):
        return None
    pos = 8
    while pos + 8 <= len(head):
        length = int.from_bytes(head[pos:pos + 4], "big")
        kind = head[pos + 4:pos + 8]
        body = head[pos + 8:pos + 8 + length]
        if kind == b"tEXt" and body.startswith(b"Software\x00"):
            return _program_of(body.split(b"\x00", 1)[1].decode("latin-1"))
        if kind in (b"IDAT", b"IEND"):
            return None
        pos += 12 + length
    return None


def foreign_entry(folder: Path) -> str | None:
    """The first entry of ``folder`` that synth did not write (None: all of it is a synth stack).

    A synth stack folder holds stack.toml (written by synth), truth.json, the images truth.json
    lists and their truth maps under truth/; an empty folder holds nothing foreign.
    """
    entries = sorted(p.name for p in folder.iterdir())
    if not entries:
        return None
    stack_toml, truth_json = folder / "stack.toml", folder / "truth.json"
    try:
        first_line = stack_toml.read_text().split("\n", 1)[0] if stack_toml.is_file() else ""
        truth = (json.loads(truth_json.read_text())
                 if truth_json.is_file() and truth_json.stat().st_size <= MAX_JSON_BYTES else None)
    except (OSError, ValueError, RecursionError):
        truth = None
    if not first_line.startswith("# Written by synth") or not isinstance(truth, dict):
        return entries[0]
    images = truth.get("images") if isinstance(truth.get("images"), list) else []
    files = {im.get("file") for im in images if isinstance(im, dict)}
    maps = {im.get("maps") for im in images if isinstance(im, dict)}
    expected = {"stack.toml", "truth.json", "truth"} | files
    for name in entries:
        p = folder / name
        if name not in expected or p.is_symlink() or (name != "truth" and not p.is_file()):
            return name
    truth_dir = folder / "truth"
    if truth_dir.exists():
        if truth_dir.is_symlink() or not truth_dir.is_dir():
            return "truth"
        for p in truth_dir.iterdir():
            if f"truth/{p.name}" not in maps or p.is_symlink() or not p.is_file():
                return f"truth/{p.name}"
    return None


def check_output(path: str | Path, option: str, *, force: bool, folder: bool = False) -> Path:
    """Refuse, before any work, an output that cannot or may not be written.

    ``folder=False``: a file whose parent folder exists; an existing file only with ``force``
    and only if lensfit or synth wrote it. ``folder=True``: a new or empty folder, or with
    ``force`` a stack folder synth wrote (nothing else in it).
    """
    path = Path(path)
    if folder:
        if path.exists() and not path.is_dir():
            raise OutputError(f"{option} {path} is an existing file; give a folder path")
        if path.is_symlink():
            raise OutputError(f"{option} {path} is a symbolic link; give a real folder path")
        if path.is_dir() and any(path.iterdir()):
            other = foreign_entry(path)
            if other is not None:
                raise OutputError(f"{option} {path} holds files synth did not write (e.g. {other!r}); choose a new "
                                  "or empty folder (--force replaces only a stack folder synth wrote)")
            if not force:
                raise OutputError(f"{option} {path} holds a stack synth wrote; pass --force to replace it")
        parent = path.parent
    else:
        if path.is_dir():
            raise OutputError(f"{option} {path} is a folder; give a file name, e.g. {path / 'results.json'}")
        if path.exists() or path.is_symlink():
            who = written_by(path)
            if who is None:
                raise OutputError(f"{option} {path} exists and was not written by lensfit or synth; choose another "
                                  "name (--force replaces only their own outputs)")
            if not force:
                raise OutputError(f"{option} {path} already exists (written by {who}); pass --force to replace it")
        parent = path.parent
        if not parent.is_dir():
            raise OutputError(f"{option} {path}: folder {parent} does not exist; create it or choose another path")
    anchor = parent
    while not anchor.exists():
        anchor = anchor.parent
    if not os.access(anchor, os.W_OK):
        raise OutputError(f"{option} {path}: folder {anchor} is not writable; choose another path")
    return path


@contextlib.contextmanager
def claimed(outputs: Iterable[tuple[str, str | Path]], *, force: bool, folder: bool = False) -> Iterator[list[Path]]:
    """Check the outputs (:func:`check_output`), lock them (:class:`OutputLock`) and check again
    under the lock, for the duration of the block; yields their paths."""
    outputs = [(opt, Path(p)) for opt, p in outputs]
    for opt, p in outputs:
        check_output(p, opt, force=force, folder=folder)
        if folder:
            p.parent.mkdir(parents=True, exist_ok=True)
    with OutputLock(outputs):
        for opt, p in outputs:
            check_output(p, opt, force=force, folder=folder)
        yield [p for _, p in outputs]


def _lock_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class OutputLock:
    """Exclusive locks on outputs for the duration of a ``with`` block (see the module notes).

    Parameters
    ----------
    outputs : iterable of (option, path)
        Each output with the option the user gave it by, for the message.
    """

    def __init__(self, outputs: Iterable[tuple[str, str | Path]]):
        self.outputs = [(opt, Path(p)) for opt, p in outputs]
        self._held: list[Path] = []

    def __enter__(self) -> "OutputLock":
        try:
            for opt, path in self.outputs:
                self._acquire(opt, path)
        except BaseException:
            self.release()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def _acquire(self, option: str, path: Path) -> None:
        lock = _lock_path(path)
        me = f"{os.getpid()} {socket.gethostname()}\n"
        for _ in range(2):
            try:
                fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                try:
                    pid_text, host = (lock.read_text().split() + ["", ""])[:2]
                    pid = int(pid_text)
                except (OSError, ValueError):
                    pid, host = -1, ""
                if pid > 0 and host == socket.gethostname() and not _pid_alive(pid):
                    lock.unlink(missing_ok=True)  # stale: its writer is gone
                    continue
                who = f"process {pid}" if pid > 0 else "another run"
                raise OutputError(f"{option} {path} is being written by {who} (lock {lock}); wait for it to "
                                  "finish or choose another path; delete the lock only if no such run exists") from None
            self._held.append(lock)  # (before writing: a full disk fails the write, and the lock must go)
            with os.fdopen(fd, "w") as fh:
                fh.write(me)
            return
        raise OutputError(f"{option} {path}: could not lock {lock}; delete it if no run is writing there")

    def release(self) -> None:
        for lock in self._held:
            lock.unlink(missing_ok=True)
        self._held.clear()


def temporary_sibling(path: Path) -> Path:
    """A unique temporary name beside ``path`` with the same suffix (writers pick formats by suffix)."""
    return path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.partial{path.suffix}")


def place(tmp: Path, final: Path, *, force: bool) -> None:
    """Rename ``tmp`` to ``final``; without ``force`` never over an existing file (atomic create)."""
    if force:
        os.replace(tmp, final)
        return
    try:
        os.link(tmp, final)
    except FileExistsError:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{final} appeared while this run was working (another program wrote it); "
                          "nothing was replaced") from None
    except OSError:  # file systems without hard links: exclusive create has no atomic rename
        if final.exists():
            tmp.unlink(missing_ok=True)
            raise OutputError(f"{final} appeared while this run was working; nothing was replaced") from None
        os.replace(tmp, final)
        return
    tmp.unlink()


def write_all(files: Iterable[tuple[Path, Callable[[Path], None]]], *, force: bool) -> list[Path]:
    """Write every ``(final path, writer(tmp_path))`` to a temporary sibling, then place them all.

    An error (or a signal) before the last rename leaves no temporary file behind; files
    already placed by this call stay (they are complete).
    """
    pending: list[tuple[Path, Path]] = []
    try:
        for final, writer in files:
            final = Path(final)
            tmp = temporary_sibling(final)
            pending.append((tmp, final))
            writer(tmp)
        from lensfit.runtime.running import check_interrupted

        check_interrupted()
        placed = []
        for tmp, final in pending:
            place(tmp, final, force=force)
            placed.append(final)
        return placed
    finally:
        for tmp, _ in pending:
            tmp.unlink(missing_ok=True)


def write_folder(out: str | Path, writer: Callable[[Path], None], *, force: bool, option: str = "--out") -> Path:
    """A folder, all or nothing: ``writer(tmp)`` fills a temporary sibling folder, which is then
    renamed into place. An existing folder is replaced only with ``force`` and only when
    :func:`check_output` allows it (a stack synth wrote, nothing else in it), checked again just
    before the swap; its old contents are removed only then, and put back if the swap fails.
    An error or a stop signal before the swap leaves nothing behind."""
    import shutil
    import tempfile

    out = check_output(out, option, force=force, folder=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    tmp.chmod(0o755)
    try:
        writer(tmp)
        from lensfit.runtime.running import check_interrupted

        check_interrupted()  # a stop signal, even one a C callback swallowed: nothing is put in place
        check_output(out, option, force=force, folder=True)  # again: something may have appeared meanwhile
        if out.is_dir() and any(out.iterdir()):
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            out.rename(old / out.name)
            try:
                tmp.rename(out)
            except BaseException:
                (old / out.name).rename(out)  # put the old folder back
                raise
            shutil.rmtree(old, ignore_errors=True)  # one check_output allowed replacing (ours, nothing else)
        else:
            tmp.rename(out)  # over an empty folder, or a new name
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def write_text(path: str | Path, text: str, *, force: bool = True) -> Path:
    """One text file, atomically (a temporary sibling, then renamed)."""
    path = Path(path)
    write_all([(path, lambda tmp: tmp.write_text(text))], force=force)
    return path
