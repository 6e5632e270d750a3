"""Hostile inputs: data loss, escapes from the stack folder, memory bombs, signals, races,
absurd numbers. Every case must end in a one-line refusal with a non-zero exit (or a typed
refusal from the API), never a traceback, never a lost or half-written file, never a read
outside the stack folder.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from lensfit.cli import main as lensfit_main
from lensfit.errors import InputError, OutputError, SpecError
from lensfit.outputs.writers import OutputLock, check_output, written_by
from lensfit.io.images import read_image
from lensfit.io.stack import load_stack
from synth.cli import main as synth_main

SCENE = """
[camera]
pixel_pitch_mm = 0.006
width_px = 96
height_px = 64

[lens]
focal_length_mm = 50.0
f_number = 4.0
focus_distance_mm = 1500.0

[render]
samples_per_pixel = 16

[[object]]
id = "board"
target = "checkerboard"
squares = [4, 3]
square_mm = 8.0
distance_mm = 1200.0
"""

REC709 = np.array([0.2126, 0.7152, 0.0722])
BIN = Path(sys.executable).parent


def one_line_error(err: str, *needles: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "error:" in lines[0], err
    for n in needles:
        assert n in lines[0], lines[0]


def run_cli(capsys, main, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def scene_file(tmp_path, text=SCENE):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def samples_json(path: Path) -> Path:
    """A samples file as lensfit measure writes it: a V of blur against distance (thin lens,
    f 50 mm, f/4, focus 1500 mm, pitch 6 um), written out independently of lensfit."""
    f, N, D, p = 50.0, 4.0, 1500.0, 0.006
    s = f * D / (D - f)
    rows = []
    for i, d in enumerate(np.linspace(700.0, 4000.0, 24)):
        c = (f / N) * s * abs(1 / D - 1 / d) / p
        rows.append({"image": f"shot_{i % 6}.png", "setting": "a", "distance_mm": float(d),
                     "coc_diameter_px": float(c), "sigma_px": 0.05})
    path.write_text(json.dumps({"samples": rows, "pixel_pitch_mm": p}))
    return path


# --------------------------------------------------------------------------- outputs: never lose data


def test_force_never_deletes_a_folder_synth_did_not_write(tmp_path, capsys):
    scene = scene_file(tmp_path)
    out = tmp_path / "photos"
    (out / "raw").mkdir(parents=True)
    (out / "IMG_0001.CR2").write_bytes(b"a user's photo")
    (out / "raw" / "IMG_0002.CR2").write_bytes(b"another")
    code, _, err = run_cli(capsys, synth_main, "render", scene, "--out", out, "--force")
    assert code == 2
    one_line_error(err, "--out", "did not write")
    assert "pass --force" not in err  # the error must not suggest the flag that would not help
    assert (out / "IMG_0001.CR2").read_bytes() == b"a user's photo"
    assert (out / "raw" / "IMG_0002.CR2").read_bytes() == b"another"


def test_force_replaces_a_stack_synth_wrote_but_not_one_a_user_added_to(tmp_path, capsys):
    scene = scene_file(tmp_path)
    out = tmp_path / "stack"
    assert run_cli(capsys, synth_main, "render", scene, "--out", out)[0] == 0
    code, _, err = run_cli(capsys, synth_main, "render", scene, "--out", out)
    assert code == 2
    one_line_error(err, "--force")  # synth's own stack: --force would replace it
    assert run_cli(capsys, synth_main, "render", scene, "--out", out, "--force", "--seed", "3")[0] == 0
    assert json.loads((out / "truth.json").read_text())["seed"] == 3
    (out / "notes.txt").write_text("my notes on this stack")
    code, _, err = run_cli(capsys, synth_main, "render", scene, "--out", out, "--force")
    assert code == 2
    one_line_error(err, "notes.txt")
    assert (out / "notes.txt").read_text() == "my notes on this stack"
    assert json.loads((out / "truth.json").read_text())["seed"] == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary or lock left


def test_fit_force_replaces_only_its_own_files(tmp_path, capsys):
    samples = samples_json(tmp_path / "samples.json")
    user = tmp_path / "results.json"
    user.write_text('{"my": "own results"}')
    args = ("fit", samples, "--focal-length-px", 8333.3, "--pixel-pitch", 0.006)
    code, _, err = run_cli(capsys, lensfit_main, *args, "--out", user, "--force")
    assert code == 2
    one_line_error(err, "--out", "not written by lensfit")
    assert user.read_text() == '{"my": "own results"}'
    ours = tmp_path / "ours.json"
    plot = tmp_path / "fit.png"
    assert run_cli(capsys, lensfit_main, *args, "--out", ours, "--plot", plot)[0] in (0, 3)
    assert written_by(ours) == "lensfit" and written_by(plot) == "lensfit"
    code, _, err = run_cli(capsys, lensfit_main, *args, "--out", ours)
    assert code == 2
    one_line_error(err, "--force")
    assert run_cli(capsys, lensfit_main, *args, "--out", ours, "--plot", plot, "--force")[0] in (0, 3)
    folder = tmp_path / "a_folder"
    folder.mkdir()
    code, _, err = run_cli(capsys, lensfit_main, *args, "--out", folder, "--force")
    assert code == 2
    one_line_error(err, "is a folder")
    code, _, err = run_cli(capsys, lensfit_main, *args, "--out", samples, "--force")
    assert code == 2 and samples.is_file()


@pytest.mark.parametrize("suffix", [".png", ".svg", ".pdf"])
def test_written_by_tells_our_plots_from_a_users(tmp_path, suffix):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from lensfit.outputs.plots import creator

    fig = plt.figure()
    fig.savefig(tmp_path / f"ours{suffix}", metadata=creator(tmp_path / f"ours{suffix}"))
    fig.savefig(tmp_path / f"users{suffix}")
    plt.close(fig)
    assert written_by(tmp_path / f"ours{suffix}") == "lensfit"
    assert written_by(tmp_path / f"users{suffix}") is None


def test_written_by_samples_csv_and_json(tmp_path, calibration_samples):
    calibration_samples.write(tmp_path / "s.csv")
    calibration_samples.write(tmp_path / "s.json")
    assert written_by(tmp_path / "s.csv") == "lensfit" and written_by(tmp_path / "s.json") == "lensfit"
    (tmp_path / "u.csv").write_text("image,setting,distance\nx,a,1\n")
    (tmp_path / "u.json").write_text('{"provenance": {"program": "excel"}}')
    assert written_by(tmp_path / "u.csv") is None and written_by(tmp_path / "u.json") is None
    (tmp_path / "link.json").symlink_to(tmp_path / "s.json")
    assert written_by(tmp_path / "link.json") is None  # never replace through a link


def test_lock_excludes_a_second_writer_and_stale_locks_are_taken_over(tmp_path):
    out = tmp_path / "results.json"
    with OutputLock([("--out", out)]):
        with pytest.raises(OutputError, match=f"process {os.getpid()}"):
            with OutputLock([("--out", out)]):
                pass
    assert not (tmp_path / ".results.json.lock").exists()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    import socket

    (tmp_path / ".results.json.lock").write_text(f"{dead.pid} {socket.gethostname()}\n")
    with OutputLock([("--out", out)]):  # the writer that left it is gone
        pass


def _cli(name: str) -> list[str]:
    return [str(BIN / name)]


def _default_sigint() -> None:
    """For a child that is to be sent Ctrl-C: an ignored SIGINT is inherited (a shell's background
    job, or a test runner whose worker pools set it), and a program rightly keeps ignoring it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_two_renders_to_one_new_folder_one_wins_intact(tmp_path):
    scene = scene_file(tmp_path)
    out = tmp_path / "stack"
    procs = [subprocess.Popen(_cli("synth") + ["render", str(scene), "--out", str(out)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), p.stdout.read(), p.stderr.read()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    loser = next(r for r in results if r[0] == 2)
    one_line_error(loser[2], "--out")
    truth = json.loads((out / "truth.json").read_text())
    assert all((out / im["file"]).is_file() for im in truth["images"])
    assert load_stack(out).images  # a complete, valid stack
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml", "stack"]


def test_two_fits_to_one_output_one_wins_intact(tmp_path):
    samples = samples_json(tmp_path / "samples.json")
    out = tmp_path / "r.json"
    cmd = _cli("lensfit") + ["fit", str(samples), "--focal-length-px", "8333.3", "--pixel-pitch", "0.006",
                             "--out", str(out)]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), p.stdout.read(), p.stderr.read()) for p in procs]
    assert sorted(r[0] == 2 for r in results) == [False, True], results
    winner = next(r for r in results if r[0] != 2)
    loser = next(r for r in results if r[0] == 2)
    one_line_error(loser[2], "--out")
    doc = json.loads(out.read_text())
    assert doc["provenance"]["program"] == "lensfit" and "a" in doc["settings"]
    assert winner[0] in (0, 3)


@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_render_exits_cleanly_and_leaves_nothing(tmp_path, sig, code):
    slow = SCENE.replace("width_px = 96", "width_px = 1200").replace("height_px = 64", "height_px = 800") \
        .replace("samples_per_pixel = 16", "samples_per_pixel = 1024") + '\n[[shot]]\n' * 15
    # (16 shots: the ray tracer leaves a board's constant regions unsampled, and four shots could
    # finish within the second the signal waits, which the test then took for no signal at all)
    scene = scene_file(tmp_path, slow.replace("[render]", '[render]\nmethod = "raytrace"'))
    out = tmp_path / "stack"
    proc = subprocess.Popen(_cli("synth") + ["render", str(scene), "--out", str(out)], preexec_fn=_default_sigint,
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lock = tmp_path / ".stack.lock"
    deadline = time.time() + 120
    while not lock.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()
    time.sleep(1.0)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    one_line_error(err, "temporary files removed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]


def test_measure_refuses_a_bad_output_before_any_work(tmp_path, capsys, monkeypatch, calibration_stack):
    import lensfit.measurement.measure

    def must_not_run(*a, **k):
        raise AssertionError("measured before checking the output")

    monkeypatch.setattr(lensfit.measurement.measure, "measure", must_not_run)
    code, _, err = run_cli(capsys, lensfit_main, "measure", calibration_stack, "--out", tmp_path / "no" / "s.csv")
    assert code == 2
    one_line_error(err, "does not exist")
    (tmp_path / "mine.csv").write_text("a,b\n1,2\n")
    code, _, err = run_cli(capsys, lensfit_main, "measure", calibration_stack, "--out", tmp_path / "mine.csv",
                           "--force")
    assert code == 2
    one_line_error(err, "not written by lensfit")
    assert (tmp_path / "mine.csv").read_text() == "a,b\n1,2\n"


def test_unforeseen_failure_is_one_line(capsys, monkeypatch):
    import lensfit.cli

    def broken(args):
        raise RuntimeError("something nobody planned for")

    monkeypatch.setattr(lensfit.cli, "dof_command", broken)
    code, _, err = run_cli(capsys, lensfit_main, "dof", "--focal-length", 50, "--f-number", 2, "--focus-distance",
                           1000, "--coc", 0.03)
    assert code == 70
    one_line_error(err, "internal error", "RuntimeError")


@pytest.mark.parametrize("thread", [False, True])
def test_quick_exit_keeps_the_output_and_the_status_and_waits_for_work(thread):
    """exit_process skips JAX's exit handlers with os._exit: what was printed (block-buffered
    into a pipe) still arrives, the status is the command's, and a thread still working is
    not cut off (the plain exit waits for it)."""
    script = ("import sys, threading, time\n"
              "import jax\n"
              "from lensfit.runtime.running import exit_process\n"
              "def late():\n"
              "    time.sleep(0.3)\n"
              "    print('thread done')\n"
              f"if {thread}:\n"
              "    threading.Thread(target=late).start()\n"
              "print('written')\n"
              "sys.stderr.write('warned')\n"
              "exit_process(3)\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # stdout block-buffered
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 3
    assert proc.stdout.split() == (["written", "thread", "done"] if thread else ["written"])
    assert proc.stderr.endswith("warned")


# --------------------------------------------------------------------------- inputs: only inside the stack


def _png(path: Path, shape=(40, 60), value=30000) -> Path:
    cv2.imwrite(str(path), np.full(shape, value, np.uint16))
    return path


def _stack(folder: Path, file: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "stack.toml").write_text(f'[camera]\npixel_pitch_mm = 0.006\n\n[[target]]\nid = "board"\n'
                                       'kind = "checkerboard"\nsquares = [6, 4]\nsquare_mm = 20.0\n\n'
                                       f'[[image]]\nfile = "{file}"\n')
    return folder


@pytest.mark.parametrize("how", ["parent", "absolute", "symlink"])
def test_image_entries_outside_the_stack_are_refused(tmp_path, how):
    outside = _png(tmp_path / "outside.png")
    folder = tmp_path / "stack"
    folder.mkdir()
    if how == "parent":
        entry = "../outside.png"
    elif how == "absolute":
        entry = str(outside)
    else:
        (folder / "inside.png").symlink_to(outside)
        entry = "inside.png"
    _stack(folder, entry)
    with pytest.raises(SpecError, match=r"image\[0\]\.file.*outside the stack folder"):
        load_stack(folder)
    stack = load_stack(folder, allow_outside=True)  # the explicit opt-in
    assert stack.read(0).mean() == pytest.approx(30000 / 65535)


@pytest.mark.parametrize("what", ["file", "folder"])
def test_a_link_swapped_in_after_the_check_is_not_followed_out_of_the_stack(tmp_path, what):
    """The names were checked when the stack was loaded; an image (or the folder it sits in)
    replaced by a link to a file outside before it is read is refused when read, naming it, and
    never decoded; read as it was, it reads."""
    (tmp_path / "secret").mkdir()
    outside = _png(tmp_path / "secret" / "outside.png", value=60000)
    folder = tmp_path / "stack"
    (folder / "sub").mkdir(parents=True)
    inside = _png(folder / "sub" / "a.png")
    _stack(folder, "sub/a.png")
    stack = load_stack(folder)
    assert stack.read(0).mean() == pytest.approx(30000 / 65535)
    if what == "file":
        inside.unlink()
        inside.symlink_to(outside)
    else:
        (folder / "sub").rename(tmp_path / "moved")
        (folder / "sub").symlink_to(tmp_path / "secret")
        (tmp_path / "secret" / "a.png").symlink_to(outside)
    with pytest.raises(SpecError, match="a.png.*outside the stack folder"):
        stack.read(0)


def test_a_huge_sparse_image_file_is_refused_unread(tmp_path):
    """A file of 4 GB (sparse: small on disk) under an image's name is refused from its size before
    a byte of it is read into memory, naming it."""
    folder = tmp_path / "stack"
    folder.mkdir()
    _png(folder / "a.png")
    _stack(folder, "a.png")
    stack = load_stack(folder)
    with (folder / "a.png").open("r+b") as fh:
        fh.truncate(4 * 1024**3)
    with pytest.raises(SpecError, match=r"a\.png.*4\.3 GB.*max-megapixels"):
        stack.read(0)


def test_etc_passwd_is_not_read(tmp_path, capsys):
    folder = _stack(tmp_path / "stack", "../../../../../../../../etc/passwd")
    code, _, err = run_cli(capsys, lensfit_main, "fit", folder)
    assert code == 2
    one_line_error(err, "image[0].file", "outside")


# --------------------------------------------------------------------------- full bit depth, every layout


def _expected_grey(rgb: np.ndarray, full: float) -> np.ndarray:
    return (rgb.astype(np.float64) / full) @ REC709


def test_16_bit_colour_png_is_read_at_16_bits_like_the_same_tiff(tmp_path):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 65536, (30, 50, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "c.png"), rgb[..., ::-1])  # OpenCV writes BGR
    tifffile.imwrite(tmp_path / "c.tif", rgb, photometric="rgb")
    tifffile.imwrite(tmp_path / "p.tif", np.moveaxis(rgb, -1, 0), photometric="rgb", planarconfig="separate")
    want = _expected_grey(rgb, 65535.0)
    for name in ("c.png", "c.tif", "p.tif"):
        np.testing.assert_allclose(read_image(tmp_path / name), want, rtol=0, atol=1e-12, err_msg=name)


def test_every_png_layout(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(2)
    grey8 = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    rgba16 = rng.integers(0, 65536, (20, 30, 4), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "rgba16.png"), rgba16[..., [2, 1, 0, 3]])
    np.testing.assert_allclose(read_image(tmp_path / "rgba16.png"), _expected_grey(rgba16[..., :3], 65535.0),
                               atol=1e-12)
    Image.fromarray(grey8, "L").save(tmp_path / "l.png")
    np.testing.assert_allclose(read_image(tmp_path / "l.png"), grey8 / 255.0, atol=1e-12)
    la = np.stack([grey8, np.full_like(grey8, 200)], axis=-1)
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    np.testing.assert_allclose(read_image(tmp_path / "la.png"), grey8 / 255.0, atol=1e-9)
    pal = Image.fromarray(grey8 // 64, "P")
    pal.putpalette([0, 0, 0, 255, 0, 0, 0, 255, 0, 0, 0, 255] + [0] * 756)
    pal.save(tmp_path / "p.png")
    colours = np.array([[0, 0, 0], [255, 0, 0], [0, 255, 0], [0, 0, 255]])[grey8 // 64]
    np.testing.assert_allclose(read_image(tmp_path / "p.png"), _expected_grey(colours, 255.0), atol=1e-9)
    bits = grey8 > 127
    Image.fromarray(bits).convert("1").save(tmp_path / "b.png")
    np.testing.assert_allclose(read_image(tmp_path / "b.png"), bits.astype(float), atol=1e-12)


# --------------------------------------------------------------------------- bombs and broken files


def _patch_png_size(src: Path, dst: Path, width: int, height: int) -> Path:
    data = bytearray(src.read_bytes())
    data[16:20], data[20:24] = width.to_bytes(4, "big"), height.to_bytes(4, "big")
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")
    dst.write_bytes(bytes(data))
    return dst


def test_png_declaring_13000_squared_is_refused_from_its_header(tmp_path, capsys):
    bomb = _patch_png_size(_png(tmp_path / "small.png"), tmp_path / "bomb.png", 13000, 13000)
    assert bomb.stat().st_size < 2000
    with pytest.raises(SpecError, match="169.0 MP.*--max-megapixels"):
        read_image(bomb)
    folder = tmp_path / "stack"
    folder.mkdir()
    bomb.rename(folder / "bomb.png")
    _stack(folder, "bomb.png")
    code, _, err = run_cli(capsys, lensfit_main, "fit", folder)
    assert code == 2
    one_line_error(err, "bomb.png", "MP")
    code, _, err = run_cli(capsys, lensfit_main, "fit", folder, "--max-megapixels", "nan")
    assert code == 2
    one_line_error(err, "--max-megapixels")


def test_compressed_tiff_bomb_is_refused_before_decoding(tmp_path):
    path = tmp_path / "bomb.tif"
    tile = np.zeros((1024, 1024), np.uint8)
    tifffile.imwrite(path, (tile for _ in range(20 * 20)), shape=(20480, 20480), dtype=np.uint8,
                     compression="zlib", tile=(1024, 1024))
    assert path.stat().st_size < 50_000_000
    with pytest.raises(SpecError, match="419.4 MP"):
        read_image(path)


@pytest.mark.parametrize("name,content", [
    ("truncated.png", None), ("garbage.png", b"not an image at all" * 10), ("empty.tif", b""),
    ("garbage.tif", b"II*\x00" + b"\xff" * 64), ("garbage.dng", b"\x00" * 512), ("garbage.cr2", b"MM\x00*" * 40),
    ("text.jpg", b"\xff\xd8\xff"),
])
def test_broken_files_are_one_line_refusals(tmp_path, capsys, name, content):
    folder = tmp_path / "stack"
    folder.mkdir()
    if content is None:
        full = _png(tmp_path / "full.png", (200, 300)).read_bytes()
        (folder / name).write_bytes(full[: len(full) // 2])
    else:
        (folder / name).write_bytes(content)
    _stack(folder, name)
    code, _, err = run_cli(capsys, lensfit_main, "measure", folder, "--out", tmp_path / "s.csv")
    assert code == 2
    one_line_error(err, name)
    assert not (tmp_path / "s.csv").exists()


@pytest.mark.parametrize("name", ["samples.json", "samples.csv"])
def test_a_missing_samples_file_is_named_as_such(tmp_path, capsys, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(capsys, lensfit_main, "fit", name)
    assert code == 2
    one_line_error(err, name)
    assert "no such samples file" in err and "stack.toml" not in err


# --------------------------------------------------------------------------- numbers


@pytest.mark.parametrize("line,field", [
    ("pixel_pitch_mm = nan", "camera.pixel_pitch_mm"), ("pixel_pitch_mm = inf", "camera.pixel_pitch_mm"),
    ("pixel_pitch_mm = 1e300", "camera.pixel_pitch_mm"), ("pixel_pitch_mm = -0.006", "camera.pixel_pitch_mm"),
])
def test_manifest_numbers_that_are_not_physical_are_refused(tmp_path, capsys, line, field):
    folder = tmp_path / "stack"
    folder.mkdir()
    _png(folder / "a.png")
    (folder / "stack.toml").write_text(f'[camera]\n{line}\n\n[[image]]\nfile = "a.png"\n')
    code, _, err = run_cli(capsys, lensfit_main, "measure", folder, "--out", tmp_path / "s.csv")
    assert code == 2
    one_line_error(err, field)


@pytest.mark.parametrize("old,new,field", [
    ("f_number = 4.0", "f_number = nan", "lens.f_number"),
    ("f_number = 4.0", "f_number = 0.3", "lens.f_number"),
    ("pixel_pitch_mm = 0.006", "pixel_pitch_mm = 1e300", "camera.pixel_pitch_mm"),
    ("distance_mm = 1200.0", "distance_mm = -inf", "object[0].distance_mm"),
    ("[[object]]", "[background]\nvalue = 1e308\n\n[[object]]", "background.value"),
])
def test_scene_numbers_that_are_not_physical_are_refused(tmp_path, capsys, old, new, field):
    scene = scene_file(tmp_path, SCENE.replace(old, new))
    code, _, err = run_cli(capsys, synth_main, "plan", scene)
    assert code == 2
    one_line_error(err, field)


def test_render_resources_are_checked_before_allocation(tmp_path, capsys):
    scene = scene_file(tmp_path)
    code, _, err = run_cli(capsys, synth_main, "render", scene, "--out", tmp_path / "o", "--spp", 10**9)
    assert code == 2
    one_line_error(err, "--spp")
    hair = scene_file(tmp_path, SCENE.replace("focus_distance_mm = 1500.0", "focus_distance_mm = 50.000001"))
    code, _, err = run_cli(capsys, synth_main, "render", hair, "--out", tmp_path / "o", "--method", "convolve")
    assert code == 2
    one_line_error(err, "--method", "PiB")
    code, out, err = run_cli(capsys, synth_main, "plan", hair)  # auto: ray traces, memory bounded by its tiles
    assert code == 0 and "raytrace" in out
    assert not (tmp_path / "o").exists()


def test_wide_image_at_most_samples_plans_within_two_tiles(tmp_path, capsys):
    # The tracer's tiles are lists of pixels (since 2026-11-27; rows before, when a row of 20 000
    # px at 65 536 spp, 125 GB, was refused): its memory no longer grows with the width, so the
    # most samples the sampler has are planned; one more is refused naming the option.
    wide = scene_file(tmp_path, SCENE.replace("width_px = 96", "width_px = 20000"))
    code, out, err = run_cli(capsys, synth_main, "plan", wide, "--spp", 65536, "--method", "raytrace")
    assert code == 0 and "raytrace" in out
    code, _, err = run_cli(capsys, synth_main, "plan", wide, "--spp", 65537, "--method", "raytrace")
    assert code == 2
    one_line_error(err, "--spp", "65536")


def _extreme(rng, lo, hi, n):
    kind = rng.integers(4)
    if kind == 0:
        return 10 ** rng.uniform(math.log10(lo), math.log10(hi), n)
    if kind == 1:
        return np.full(n, 10 ** rng.uniform(math.log10(lo), math.log10(hi)))
    if kind == 2:
        return np.full(n, rng.choice([lo, hi]))
    return 10 ** rng.uniform(math.log10(lo), math.log10(hi)) * (1 + 1e-9 * rng.normal(size=n))


def test_fit_never_crashes_or_returns_nan_on_extreme_finite_samples():
    """Random sample sets at the edges of the valid ranges (and beyond them): a result without
    NaN or inf (estimates or typed reasons), or an InputError naming the field; nothing else."""
    import warnings

    from lensfit.fitting import fit

    rng = np.random.default_rng(20261123)
    outcomes = {"ok": 0, "not_identifiable": 0, "InputError": 0}
    for trial in range(60):
        n = int(rng.integers(1, 30))
        widen = 1e3 if trial % 4 == 0 else 1.0  # a quarter of the sets go beyond the valid ranges
        d = _extreme(rng, 0.1 / widen, 1e9 * widen, n)
        c = _extreme(rng, 1e-9, 1e6 * widen, n) * rng.choice([0.0, 1.0], n, p=[0.1, 0.9])
        sg = _extreme(rng, 1e-6 / widen, 1e6, n)
        rows = [{"setting": str(rng.choice(["a", "b"])), "distance_mm": float(a), "coc_diameter_px": float(b),
                 "sigma_px": float(e)} for a, b, e in zip(d, c, sg)]
        pitch = float(_extreme(rng, 1e-4, 1.0 * widen, 1)[0])
        fpx = float(_extreme(rng, 1.0, 1e7, 1)[0]) if rng.random() < 0.8 else None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # no RuntimeWarning escapes either
                result = fit(rows, pixel_pitch_mm=pitch, focal_length_px=fpx)
        except InputError as exc:
            assert exc.argument in ("pixel_pitch_mm", "focal_length_px", "samples") or \
                exc.argument.startswith("samples["), exc
            outcomes["InputError"] += 1
            continue
        json.dumps(result.to_json_dict(), allow_nan=False)
        assert result.ok or result.reasons
        outcomes[result.code] += 1
    assert outcomes["InputError"] >= 5 and outcomes["not_identifiable"] + outcomes["ok"] >= 30, outcomes


def test_check_output_refuses_an_unwritable_folder(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes everywhere")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    with pytest.raises(OutputError, match="not writable"):
        check_output(ro / "r.json", "--out", force=False)


@pytest.mark.parametrize("name,content", [
    ("s.csv", b"\xff\xfe\x00binary\x00\x81"), ("s.csv", b"setting,distance_mm\na,1000\n"),
    ("s.csv", b"setting,distance_mm,coc_diameter_px,sigma_px\na,nan,3,0.1\n"),
    ("s.csv", b"setting,distance_mm,coc_diameter_px,sigma_px\na,ten,3,0.1\n"),
    ("s.json", b"[[1, 2], [3]]"), ("s.json", b'{"samples": [[1, 2]]}'),
    ("s.json", b'{"samples": [], "intrinsics": {"a": 5}}'), ("s.json", b'{"samples": "x", "pixel_pitch_mm": 0.006}'),
    ("s.json", b'{"samples": [{"setting": "a", "distance_mm": 1e400, "coc_diameter_px": 1, "sigma_px": 1}]}'),
    ("s.json", b"\x00\x01\x02"),
    ("s.json", b'{"samples": [], "samples": []}'), ("s.json", b"[" * 100000 + b"]" * 100000),
    ("s.csv", b"setting,distance_mm,coc_diameter_px,sigma_px,sigma_px\na,1000,3,0.1,0.2\n"),
    ("s.csv", b"setting,distance_mm,coc_diameter_px,sigma_px\na,1000,-3,0.1\n"),
    ("s.csv", b"setting,distance_mm,coc_diameter_px,sigma_px\na,1000,3\x00,0.1\n"),
    ("s.csv", b"setting,distance_mm,coc_diameter_px,sigma_px\n" + b"".join(
        b"s%d,%d,3,0.1\n" % (k // 2, 1000 + k) for k in range(400))),
])
def test_hostile_samples_files_are_one_line_refusals(tmp_path, capsys, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    code, _, err = run_cli(capsys, lensfit_main, "fit", path, "--pixel-pitch", 0.006, "--focal-length-px", 8000)
    assert code == 2, err
    one_line_error(err)


@pytest.mark.parametrize("edit,field,says", [
    (lambda t: t.replace('setting = "a"', 'setings = "a"', 1), "image[0].setings", "did you mean 'setting'"),
    (lambda t: t.replace("DICT_4X4_50", "DICT_NOPE_99"), "target[0].dictionary", "not an ArUco dictionary"),
    (lambda t: t.replace("marker_mm = 22.0", "marker_mm = 40.0"), "target[0].marker_mm", "smaller than square_mm"),
    (lambda t: t.replace("squares = [\n    6,\n    4,\n]", "squares = [100000, 100000]"), "target[0].squares",
     "at most 200 squares"),
    (lambda t: t.replace("squares = [\n    6,\n    4,\n]", "squares = [20, 20]"), "target[0].squares",
     "needs 200 markers"),
    (lambda t: t + t[t.index("[[image]]"):t.index("[[image]]", t.index("[[image]]") + 1)], "image[8].file",
     "lists already"),
    (lambda t: t + "a = " + "[" * 100000 + "]" * 100000 + "\n", "stack.toml", "nested too deeply"),
    (lambda t: t.replace("[camera]\n", "[camera]\ndistance_m = 3\n", 1), "camera.distance_m", "valid here"),
    (lambda t: t.replace("pixel_pitch_mm", "x_pitch", 1), "camera", "needs pixel_pitch_mm or sensor_width_mm"),
])
def test_stack_toml_typos_are_refused_naming_the_key(calibration_stack, tmp_path, capsys, edit, field, says):
    """Unknown keys in stack.toml are refused (a typo of an optional key would otherwise be
    silently ignored), with the nearest valid key; your own fields may start with x_. So are
    boards no detector can use, an image listed twice and TOML nested beyond reason: a one-line
    refusal naming the field, never an internal error."""
    import shutil

    from lensfit.io.stack import load_stack

    folder = tmp_path / "stack"
    shutil.copytree(calibration_stack, folder)
    manifest = folder / "stack.toml"
    manifest.write_text(manifest.read_text().replace("[camera]\n", "[camera]\nx_note = \"mine\"\n", 1))
    load_stack(folder)  # x_ fields are the user's own
    manifest.write_text(edit(manifest.read_text()))
    with pytest.raises(SpecError) as err:
        load_stack(folder)
    assert f"{field}:" in str(err.value) and says in str(err.value), str(err.value)
    code, _, cli_err = run_cli(capsys, lensfit_main, "fit", folder, "--out", tmp_path / "r.json")
    assert code == 2 and not (tmp_path / "r.json").exists()
    one_line_error(cli_err, field)


def test_a_ctrl_c_swallowed_by_a_callback_still_stops_the_command():
    # A KeyboardInterrupt raised inside a C callback (JAX's, during a render) is swallowed there;
    # the command must still end with 130 instead of finishing as if nothing happened.
    code = ("import os, signal, sys, time\n"
            "from lensfit.runtime.running import run_guarded\n"
            "def body():\n"
            "    try:\n"
            "        os.kill(os.getpid(), signal.SIGINT)\n"
            "        time.sleep(0.5)\n"
            "    except KeyboardInterrupt:\n"
            "        pass  # what a C callback does with it\n"
            "    return 0\n"
            "sys.exit(run_guarded('x', body))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          preexec_fn=_default_sigint)
    assert proc.returncode == 130, (proc.returncode, proc.stderr)
    assert "interrupted" in proc.stderr


def test_a_target_too_small_to_pose_is_skipped_not_an_opencv_assertion():
    """A 4-corner square a thousandth of a pixel across (thousands of metres away): IPPE gives no
    finite pose, and the SQPnP fallback refuses the points with an assertion (cv2.error, seen on a
    slanted-edge stack with the target 2 m away at 15 mm); the pose is None, so the image's
    target is skipped instead of the run crashing."""
    from lensfit.calibration.camera import Intrinsics, estimate_pose
    from lensfit.calibration.targets import Detection

    obj = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    img = 320.0 + np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float) * 1e-3
    intr = Intrinsics(3000.0, (320.0, 240.0), (0.0,) * 5, 0.0, 0, "manifest")
    assert estimate_pose(Detection("square", obj, img, np.arange(4)), intr) is None


def test_a_full_disk_is_an_error_that_leaves_nothing(tmp_path, capsys, monkeypatch):
    """A disk that fills while the outputs are written: exit 1 with a message that says so and what
    to do, no output, no temporary file and no lock left behind (a second run is not refused as
    "being written")."""
    import errno

    import lensfit.outputs.writers

    def full(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(lensfit.outputs.writers.os, "replace", full)
    monkeypatch.setattr(lensfit.outputs.writers.os, "link", full)
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_cli(capsys, lensfit_main, "target", "--out", out / "board.png")
    assert code == 1
    one_line_error(err, "No space left on device", "free some space")
    assert list(out.iterdir()) == []
    monkeypatch.undo()
    code, _, err = run_cli(capsys, lensfit_main, "target", "--out", out / "board.png")
    assert code == 0, err


def test_a_bad_value_from_a_file_is_named_as_the_files_field(tmp_path, capsys):
    """A pixel pitch of 5 (micrometres typed for mm) in a samples JSON is named as that file's
    field, not as the command-line option the user never gave."""
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"pixel_pitch_mm": 5, "samples": [
        {"setting": "a", "distance_mm": 1000.0, "coc_diameter_px": 3.0, "sigma_px": 0.1}]}))
    code, _, err = run_cli(capsys, lensfit_main, "fit", path)
    assert code == 2
    one_line_error(err, "samples.pixel_pitch_mm", "got 5")
    assert "--pixel-pitch" not in err


def test_a_huge_sparse_json_is_not_read_to_see_who_wrote_it(tmp_path):
    """A 4 GB sparse file named like lensfit's results is not ours (nothing lensfit writes is that
    large): judged from its size, not read whole (6 GB of memory before)."""
    big = tmp_path / "results.json"
    with big.open("wb") as fh:
        fh.truncate(4 * 1024**3)
    assert written_by(big) is None


def test_a_png_chunk_claiming_more_than_the_file_is_refused_before_decoding(tmp_path):
    """A PNG whose IDAT length reads 0x7FFFFFFF (the decoder allocated 2.1 GB for a 12 KB file):
    refused from its chunk table, naming the chunk and what the file holds."""
    import struct

    ok, buf = cv2.imencode(".png", np.full((40, 60), 128, np.uint8))
    data = bytearray(buf.tobytes())
    at = data.index(b"IDAT") - 4
    data[at:at + 4] = struct.pack(">I", 0x7FFFFFFF)
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(bytes(data))
    with pytest.raises(SpecError, match="'IDAT' chunk claims 2147483647 bytes"):
        read_image(bomb)


def test_a_float_tiff_without_light_is_named_not_reported_as_too_few_views(tmp_path):
    """A float TIFF whose values are all negative (a negated or difference image) was measured
    and reported as "too few views"; it is refused naming the file and what it holds. Noise dipping
    below 0 around a black level is light and is read."""
    import tifffile

    noisy = 0.2 + 0.01 * np.random.default_rng(1).standard_normal((40, 60))
    tifffile.imwrite(tmp_path / "noisy.tif", (noisy - 0.2).astype(np.float32))  # half the pixels below 0
    assert read_image(tmp_path / "noisy.tif").max() > 0
    tifffile.imwrite(tmp_path / "neg.tif", -noisy.astype(np.float32))
    with pytest.raises(SpecError, match="no positive value") as err:
        read_image(tmp_path / "neg.tif")
    assert "neg.tif" in str(err.value)


def test_a_disk_full_while_the_lock_is_written_leaves_no_lock(tmp_path, capsys, monkeypatch):
    """The disk can fill at the lock itself (its process id written into it): the run fails with
    exit 1 and the empty lock goes with it, so the next run is not refused as "being written"."""
    import errno

    import lensfit.outputs.writers

    class Full:
        def __init__(self, fd, *a, **k):
            os.close(fd)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, _):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(lensfit.outputs.writers.os, "fdopen", Full)
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_cli(capsys, lensfit_main, "target", "--out", out / "board.png")
    assert code == 1
    one_line_error(err, "No space left on device")
    assert list(out.iterdir()) == []
    monkeypatch.undo()
    code, _, err = run_cli(capsys, lensfit_main, "target", "--out", out / "board.png")
    assert code == 0, err


def test_an_error_names_the_option_typed_only_for_the_whole_argument_name():
    """A CLI maps argument names to its options in a message; a word that merely contains one
    ("without" holds "out") is left as written."""
    err = InputError("scene", "a.toml", "given only without out", "see seed_list and seed")
    text = err.describe({"out": "--out", "seed": "--seed", "scene": "--scene"})
    assert text.startswith("--scene must be given only without --out, got")
    assert InputError("x", 1, "in seed_list or seed").describe({"seed": "--seed"}).startswith(
        "x must be in seed_list or --seed, got")
