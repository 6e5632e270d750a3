"""A stack held in memory reads as the files do: the same float64 values, bit for bit, whether the
images are held as float64, held as their files' integers (a stack too large to hold as float64),
or read again from the files; and the hold keeps within its budget."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

from lensfit.io.images import HeldRaster, read_image
from lensfit.io.stack import COMPACT_HOLD_SHARE, load_stack

H, W = 48, 80


def write_stack(folder: Path, images: list[dict]) -> Path:
    """Images as 16-bit or 8-bit grey PNGs (random levels) and a stack.toml naming them."""
    folder.mkdir()
    rng = np.random.default_rng(3)
    entries = []
    for k, extra in enumerate(images):
        depth = extra.pop("depth", 16)
        levels = rng.integers(0, 2**depth, (H, W), dtype=np.uint16 if depth == 16 else np.uint8)
        name = f"shot_{k}.png"
        assert cv2.imwrite(str(folder / name), levels)
        entries.append({"file": name, "encoding": "linear", "setting": "a", "distance_mm": 1000.0 + k,
                        "targets": ["board"], **extra})
    manifest = {"camera": {"pixel_pitch_mm": 0.006},
                "target": [{"id": "board", "kind": "charuco", "squares": [6, 4], "square_mm": 30.0,
                            "marker_mm": 22.0, "dictionary": "DICT_4X4_50"}],
                "image": entries}
    (folder / "stack.toml").write_text(tomli_w.dumps(manifest))
    return folder


IMAGES = [{}, {"depth": 8}, {"black_level": 100, "white_level": 60000}, {"encoding": "srgb", "depth": 8},
          {"rotate_deg": 180}]


@pytest.mark.parametrize("limit", [10**9, 10 * H * W * 2, 3 * H * W * 2, 0],
                         ids=["float64", "four-as-integers", "one-as-integers", "none"])
def test_a_held_stack_reads_as_its_files(tmp_path, limit):
    folder = write_stack(tmp_path / "stack", [dict(e) for e in IMAGES])
    plain = load_stack(folder)
    held = load_stack(folder).holding(limit)
    for _ in range(2):  # the second time from the hold
        for i, entry in enumerate(plain.images):
            want = read_image(entry.file, entry.encoding, black_level=entry.black_level,
                              white_level=entry.white_level)
            if entry.rotate_deg:
                want = np.rot90(want, entry.rotate_deg // 90)
            got = held.read(i)
            assert got.dtype == np.float64 and np.array_equal(got, want), entry.file.name
            assert np.array_equal(plain.read(i), want)
    hold = held.hold
    stored = [hold.get(i) for i in range(len(IMAGES))]
    kept = [s for s in stored if s is not None]
    if limit == 10**9:  # the whole stack fits as float64: every image held so
        assert len(kept) == len(IMAGES) and all(isinstance(s, np.ndarray) for s in kept)
    else:  # held as the files' integers while they fit (in the order read), the rest read again
        assert all(isinstance(s, HeldRaster) for s in kept)
        budget, total, fits = int(limit * COMPACT_HOLD_SHARE), 0, []
        for nbytes in (H * W * (2 if e.get("depth", 16) == 16 else 1) for e in IMAGES):
            fits.append(total + nbytes <= budget)
            total += nbytes if fits[-1] else 0
        assert [s is not None for s in stored] == fits
        assert sum(s.nbytes for s in kept) <= budget
        assert len(kept) == {10 * H * W * 2: 4, 3 * H * W * 2: 1, 0: 0}[limit]


def test_the_integers_are_a_fraction_of_the_float64_bytes(tmp_path):
    folder = write_stack(tmp_path / "stack", [{}, {"depth": 8}])
    stack = load_stack(folder)
    raw = [read_image(e.file, keep_integers=True) for e in stack.images]
    assert [r.nbytes for r in raw] == [H * W * 2, H * W]
    assert all(np.array_equal(r.linear(), read_image(e.file)) for r, e in zip(raw, stack.images))
