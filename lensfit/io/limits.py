"""Resource budgets checked before anything large is allocated.

Every size a file or a spec can ask for is estimated first and refused, with the number and
the option that raises the budget, before memory is taken: image pixels (from the file header,
before decoding), ray-tracing samples, blur kernels.
"""

from __future__ import annotations

#: Largest image read by default, megapixels. Above today's largest stills cameras (about 102 MP
#: medium format); an image this size takes about 3 GB while it is decoded to float64.
DEFAULT_MAX_MEGAPIXELS = 120.0

#: Largest image side, px, that any file may declare (also under a raised pixel budget).
MAX_SIDE_PX = 100_000

#: Bounds of a calibration's numbers read back from a samples file (as stack.toml's
#: [[intrinsics]] bounds them): focal length, its sigma and the principal point in px, and the
#: distortion coefficients.
INTRINSICS_MAX_PX = 1e7
DISTORTION_MAX = 1e6


def check_image_size(path, height_px: int, width_px: int, max_pixels: int) -> None:
    """Refuse an image whose header declares more than ``max_pixels`` (or an absurd side)."""
    from lensfit.errors import SpecError

    if height_px < 1 or width_px < 1:
        raise SpecError(path, "", f"declares {width_px} x {height_px} px; an image needs at least one pixel")
    if max(height_px, width_px) > MAX_SIDE_PX:
        raise SpecError(path, "", f"declares {width_px} x {height_px} px, a side above {MAX_SIDE_PX} px; "
                        "is the file corrupt?")
    if height_px * width_px > max_pixels:
        raise SpecError(path, "", f"declares {width_px} x {height_px} px = {height_px * width_px / 1e6:.1f} MP, above "
                        f"the budget of {max_pixels / 1e6:g} MP; raise it with --max-megapixels if the image is "
                        "genuine (decoding takes about 24 bytes per pixel)")


#: Memory one rendered shot may take (bytes) beyond its images: ray-tracing tiles, blur kernels
#: and FFT grids. Checked by ``synth plan`` and ``synth render`` before anything is allocated.
RENDER_MEMORY_BYTES = 4 << 30


def format_bytes(n: float) -> str:
    """``4.0 GiB``-style text."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n:.0f} B"
        n /= 1024
    return f"{n:.1f} PiB"
