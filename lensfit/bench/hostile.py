"""The hostile inputs with large counts, each run as a user would run it, timed and weighed.

``lensfit bench-hostile`` writes every input below into a scratch folder (small files: the
largest is a 1,000,001-row samples CSV of 17 MB and a sparse 4 GiB results file that holds no
data), runs the command a user would run on it in a fresh process, and records its exit
status, wall time, peak resident memory (the process's own, from ``wait4`` in a small launcher
process) and the first line it wrote to stderr. A case passes when the status is the expected one, the message is one line
naming what it should, and the run stays within ``MAX_SECONDS`` and ``MAX_PEAK_BYTES``. The fast
cases of the same kinds run in ``make test`` (``tests/io/test_hostile.py``,
``tests/io/test_schema_fields.py``); these take seconds to minutes each and run here.

``--record DIR`` writes ``DIR/hostile.json``, the table the documentation's validation page shows.
"""

from __future__ import annotations

import os
import shutil
import struct
import sys
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

#: A run's limits: what the issue that asked for this suite allowed on inputs under 2 MB.
MAX_SECONDS = 60.0
MAX_PEAK_BYTES = 1 << 30
#: A run still going after this is killed and recorded as failed.
KILL_SECONDS = 180.0


@dataclass
class Case:
    name: str
    what: str
    argv: list[str]
    expect_status: tuple[int, ...]
    expect_text: str  # in the message (the first stderr line); "" where the run should succeed


@dataclass
class Outcome:
    name: str
    what: str
    input_bytes: int
    status: int | None
    seconds: float
    peak_mib: float
    message: str
    passed: bool


def _stack_toml(images: list[str], extra: str = "", squares: str = "[6, 4]", setting: str = "a") -> str:
    head = ('[camera]\npixel_pitch_mm = 0.006\n\n[[target]]\nid = "board"\nkind = "charuco"\n'
            f'squares = {squares}\nsquare_mm = 30.0\nmarker_mm = 22.0\ndictionary = "DICT_4X4_50"\n')
    return head + extra + "".join(f'\n[[image]]\nfile = "{f}"\nsetting = "{setting}"\n' for f in images)


def _png(path: Path, size: tuple[int, int] = (40, 60)) -> bytes:
    import cv2
    import numpy as np

    ok, buf = cv2.imencode(".png", np.full(size, 128, np.uint8))
    data = buf.tobytes()
    path.write_bytes(data)
    return data


def _png_chunk_bombs(root: Path) -> Case:
    folder = root / "png_bombs"
    folder.mkdir()
    data = bytearray(_png(folder / "seed.png"))
    at = data.index(b"IDAT") - 4
    data[at:at + 4] = struct.pack(">I", 0x7FFFFFFF)
    names = []
    for i in range(12):  # each padded to 1 MB after its IEND, as the report's files were
        (folder / f"b{i}.png").write_bytes(bytes(data) + bytes((1 << 20) - len(data)))
        names.append(f"b{i}.png")
    (folder / "seed.png").unlink()
    (folder / "stack.toml").write_text(_stack_toml(names))
    return Case("png_chunk_bombs", "12 PNGs of 1 MB whose IDAT chunk claims 0x7FFFFFFF bytes",
                ["measure", str(folder), "--out", str(root / "png_bombs.csv")], (2,), "IDAT")


def _one_image_stack(root: Path, name: str, manifest: str) -> list[str]:
    """A stack folder ``root/name`` of one small PNG and the given stack.toml; the arguments of
    ``lensfit measure`` on it."""
    folder = root / name
    folder.mkdir()
    _png(folder / "a.png")
    (folder / "stack.toml").write_text(manifest)
    return ["measure", str(folder), "--out", str(root / f"{name}.csv")]


def _squares(root: Path) -> Case:
    return Case("target_squares_1e5", "a target of 100,000 x 100,000 squares",
                _one_image_stack(root, "squares", _stack_toml(["a.png"], squares="[100000, 100000]")), (2,),
                "target[0].squares")


def _many_images(root: Path) -> Case:
    folder = root / "many_images"
    folder.mkdir()
    files = [f"i{k}.png" for k in range(12)]
    for f in files:
        _png(folder / f)
    text = _stack_toml([])
    text += "".join(f'\n[[image]]\nfile = "{files[k % 12]}"\nsetting = "s{k}"\n' for k in range(100_000))
    (folder / "stack.toml").write_text(text)
    return Case("images_100k", "100,000 [[image]] entries over 12 files",
                ["measure", str(folder), "--out", str(root / "many.csv")], (2,), "image")


def _nested_toml(root: Path) -> Case:
    deep = _stack_toml(["a.png"]) + "x_deep = " + "[" * 100_000 + "]" * 100_000 + "\n"
    return Case("toml_nested_100k", "a stack.toml nested 100,000 deep", _one_image_stack(root, "nested", deep), (2,),
                "nested too deeply")


_CSV_HEAD = "setting,distance_mm,coc_diameter_px,sigma_px\n"


def _csv_rows(root: Path) -> Case:
    path = root / "rows.csv"
    with path.open("w") as fh:
        fh.write(_CSV_HEAD)
        row = "a,1000.0,3.0,0.1\n"
        for _ in range(1_000_001 // 1000):
            fh.write(row * 1000)
        fh.write(row)
    return Case("samples_csv_1M_rows", "a samples CSV of 1,000,001 rows (17 MB)",
                ["fit", str(path), "--pixel-pitch", "0.006", "--focal-length-px", "8000", "--out",
                 str(root / "rows.json")], (2,), "rows")


def _csv_settings(root: Path) -> Case:
    path = root / "settings.csv"
    lines = [_CSV_HEAD] + [f"s{k},{d},{abs(3000 / d - 2) * 20 + 1:.3f},0.1\n"
                           for k in range(1000) for d in (700, 900, 1200, 1500, 2000, 3000)]
    path.write_text("".join(lines))
    return Case("samples_csv_1000_settings", "a samples CSV of 1,000 setting labels of 6 rows",
                ["fit", str(path), "--pixel-pitch", "0.006", "--focal-length-px", "8000", "--out",
                 str(root / "settings.json")], (2,), "samples.setting")


def _nested_json(root: Path) -> Case:
    path = root / "nested.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    return Case("samples_json_nested_100k", "a samples JSON nested 100,000 deep",
                ["fit", str(path), "--pixel-pitch", "0.006", "--out", str(root / "nested_json.json")], (2,),
                "nested")


def _maker_notes(root: Path) -> Case:
    """Two photos whose maker note claims 1.9 MB (the file holds them, after the image) and
    0x7FFFFFFF bytes."""
    import numpy as np
    from PIL import Image
    from PIL.ExifTags import IFD

    folder = root / "maker_notes"
    folder.mkdir()
    for name, claim in (("big.jpg", 1_900_000), ("claims.jpg", 0x7FFFFFFF)):
        ex = Image.Exif()
        ex[0x010F], ex[0x0110] = "NIKON CORPORATION", "NIKON D850"
        ex.get_ifd(IFD.Exif)[0x927C] = bytes(64)
        Image.fromarray(np.full((48, 64), 128, np.uint8)).save(folder / name, "JPEG", exif=ex)
        data = bytearray((folder / name).read_bytes())
        order = ">" if b"Exif\x00\x00MM" in data else "<"  # the TIFF header's byte order
        at = data.index(struct.pack(order + "H", 0x927C))  # the maker note's IFD entry: tag, type, count
        data[at + 4:at + 8] = struct.pack(order + "I", claim)
        (folder / name).write_bytes(bytes(data) + bytes(min(claim, 2_000_000)))
    return Case("maker_notes", "lensfit init on maker notes claiming 1.9 MB (held) and 0x7FFFFFFF bytes",
                ["init", str(folder)], (0, 2), "")


def _photos(root: Path, count: int) -> Path:
    import numpy as np
    from PIL import Image

    folder = root / "photos"
    folder.mkdir()
    seed = root / "seed.jpg"
    Image.fromarray(np.full((16, 24), 128, np.uint8)).save(seed, "JPEG")
    for k in range(count):
        shutil.copyfile(seed, folder / f"p{k:05d}.jpg")
    seed.unlink()
    return folder


def _photos_10k(root: Path) -> Case:
    return Case("init_10k_photos", "lensfit init on 10,000 photos (more than a stack may list)",
                ["init", str(_photos(root, 10_000)), "--pixel-pitch", "0.004"], (2,), "at most 5000")


def _photos_5k(root: Path) -> Case:
    return Case("init_5k_photos_per_image", "lensfit init --settings per-image on 5,000 photos",
                ["init", str(_photos(root, 5_000)), "--settings", "per-image", "--pixel-pitch", "0.004"], (0,), "")


def _sparse_output(root: Path) -> Case:
    path = root / "sparse.csv"
    path.write_text(_CSV_HEAD + "".join(f"a,{d},{abs(1500 / d - 1) * 30 + 1:.4f},0.05\n"
                                        for d in (700, 800, 900, 1100, 1300, 1700, 2200, 3000, 4000)))
    out = root / "results.json"
    with out.open("wb") as fh:
        fh.truncate(4 << 30)  # a 4 GiB file of holes: no disk used
    return Case("sparse_4gib_output_force", "--force onto a sparse 4 GiB file at the results path",
                ["fit", str(path), "--pixel-pitch", "0.006", "--focal-length-px", "8000", "--out", str(out),
                 "--force"], (2,), "results.json")


#: The cases by name, each a function that writes its inputs under a folder and says how to run it.
CASES: dict[str, Callable[[Path], Case]] = {
    "png_chunk_bombs": _png_chunk_bombs, "target_squares_1e5": _squares, "images_100k": _many_images,
    "toml_nested_100k": _nested_toml, "samples_csv_1M_rows": _csv_rows, "samples_csv_1000_settings": _csv_settings,
    "samples_json_nested_100k": _nested_json, "maker_notes": _maker_notes, "init_10k_photos": _photos_10k,
    "init_5k_photos_per_image": _photos_5k,
    "sparse_4gib_output_force": _sparse_output}


def _input_bytes(root: Path) -> int:
    """Bytes the inputs hold on disk (a sparse file counts what it occupies)."""
    return sum(p.stat().st_blocks * 512 for p in root.rglob("*") if p.is_file())


def run_case(case: Case, before_bytes: int, root: Path | None = None) -> Outcome:
    from lensfit.bench.peak import run_with_peak

    ran = run_with_peak([sys.executable, "-m", "lensfit", *case.argv], KILL_SECONDS)
    code, seconds, peak, err = ran.status, ran.seconds, ran.peak_bytes, ran.stderr
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    message = lines[0] if lines else ""
    if root is not None:  # (the scratch folder's name says nothing)
        message = message.replace(f"{root}{os.sep}", "")
    one_line = len([ln for ln in lines if "error" in ln]) <= 1 and "Traceback" not in err
    passed = (code in case.expect_status and one_line and seconds <= MAX_SECONDS and peak <= MAX_PEAK_BYTES
              and (code == 0 or case.expect_text in message))
    return Outcome(case.name, case.what, before_bytes, code, round(seconds, 2), round(peak / (1 << 20), 1),
                   message[:300], passed)


def run(progress: Callable[[str], None] = lambda m: None, only: list[str] | None = None) -> dict[str, Any]:
    """Every case (or those named in ``only``), in a scratch folder removed afterwards."""
    outcomes = []
    with tempfile.TemporaryDirectory(prefix="lensfit-hostile-") as tmp:
        for name, make in CASES.items():
            if only and name not in only:
                continue
            progress(name)
            root = Path(tmp) / name
            root.mkdir()
            case = make(root)
            outcomes.append(run_case(case, _input_bytes(root), root))
            shutil.rmtree(root, ignore_errors=True)
    from lensfit.bench.records import record_header

    return {**record_header("hostile", "lensfit bench-hostile"), "max_seconds": MAX_SECONDS, "max_peak_mib": MAX_PEAK_BYTES >> 20,
            "cases": [asdict(o) for o in outcomes], "passed": sum(o.passed for o in outcomes),
            "total": len(outcomes)}


def markdown(doc: dict[str, Any]) -> str:
    """The record as the documentation's table."""
    out = [f"### Hostile inputs at scale ({doc['passed']} of {doc['total']} pass)", "",
           f"`{doc['command']}`, {doc['date']}, {doc['system']}, {doc['cores']} cores. A case passes with the "
           f"expected exit status, a one-line message naming the problem, at most {doc['max_seconds']:g} s and "
           f"{doc['max_peak_mib']} MiB of peak memory.", "",
           "| case | input on disk | exit | seconds | peak MiB | message | pass |", "|---|---|---|---|---|---|---|"]
    for c in doc["cases"]:
        size = c["input_bytes"]
        shown = f"{size / 1e6:.1f} MB" if size >= 1e5 else f"{size / 1e3:.0f} kB"
        msg = c["message"].replace("|", "\\|").replace("<", "&lt;")
        out.append(f"| {c['what']} | {shown} | {c['status']} | {c['seconds']:.1f} | {c['peak_mib']:.0f} | "
                   f"{msg[:160]} | {'yes' if c['passed'] else '**no**'} |")
    return "\n".join(out)
