"""Checks shared by the test modules (importable because pytest puts tests/ on sys.path)."""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path


def assert_recovered_or_refused(result, truth: dict[str, float], rel: float, k_sigma: float | None = None,
                                setting: str = "a") -> None:
    """Each quantity of ``truth`` (name -> true value) is within ``rel`` of the truth (and within
    ``k_sigma`` stated sigmas, when given), or is refused with a reason: never a silent number."""
    est = result.settings[setting]
    for q, t in truth.items():
        e = est[q]
        if e.value is None:
            assert e.reason, q
            continue
        assert abs(e.value / t - 1) < rel, (q, e.value, t)
        if k_sigma is not None:
            assert abs(e.value - t) < k_sigma * e.sigma + 1e-6 * t, (q, e.value, t, e.sigma)


def calibration_scene(**render) -> dict:
    """The conftest's calibration stack as a scene dict (8 ChArUco views, some tilted, 640 x 480,
    16 mm f/8 focused at 800 mm); ``render`` overrides [render] (e.g. method, samples_per_pixel)."""
    shots = [{"pose": [{"id": "board", "distance_mm": float(dist), "tilt_deg": tilt}]}
             for dist, tilt in [(450, [0, 0]), (550, [25, 0]), (650, [0, -30]), (800, [-20, 15]),
                                (950, [0, 25]), (1100, [20, -20]), (1300, [0, 0]), (1500, [-25, 10])]]
    return {
        "camera": {"pixel_pitch_mm": 0.006, "width_px": 640, "height_px": 480},
        "lens": {"focal_length_mm": 16.0, "f_number": 8.0, "focus_distance_mm": 800.0},
        "render": {"samples_per_pixel": 64, **render},
        "background": {"value": 0.3},
        "object": [{"id": "board", "target": "charuco", "squares": [6, 4], "square_mm": 30.0, "marker_mm": 22.0,
                    "dictionary": "DICT_4X4_50", "size_mm": [190.0, 130.0], "distance_mm": 800.0}],
        "shot": shots,
    }


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: A page's own reading of itself in the browser, stored on <body> for --dump-dom to carry out.
_PROBE = """<script>
const doc = document.documentElement, imgs = [...document.images];
const tables = [...document.querySelectorAll('table')].map(t => [...t.rows].map(r => [...r.cells].map(c => c.innerText)));
const header = (document.querySelector('p.note') || {innerText: ''}).innerText;
document.body.setAttribute('data-probe', JSON.stringify({scroll: doc.scrollWidth, client: doc.clientWidth,
  images: imgs.length, broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length,
  wide: [...document.querySelectorAll('p, h1, h2, h3, img, div.scroll')].filter(e => e.getBoundingClientRect().right > doc.clientWidth + 1).length,
  tables, header, text: document.body.innerText}));
</script></body>"""


def read_in_browser(page: Path, tmp_path: Path, width_px: int = 800) -> dict:
    """Render ``page`` in headless Chromium in a window ``width_px`` wide and return what the
    browser read of its own layout (``_PROBE``): scroll and client width, elements wider than the
    window, images and how many failed to decode, every table's cells, the first note, the text."""
    probe_page = tmp_path / f"probe-{page.name}"
    probe_page.write_text(page.read_text(encoding="utf-8").replace("</body>", _PROBE), encoding="utf-8")
    dom = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                          "--disable-background-networking", "--disable-component-update", "--disable-sync",
                          f"--user-data-dir={tmp_path / 'chromium-profile'}", f"--window-size={width_px},1000",
                          "--dump-dom", probe_page.as_uri()], capture_output=True, text=True, timeout=120,
                         check=True).stdout
    return json.loads(html.unescape(re.search(r'data-probe="([^"]*)"', dom).group(1)))


def axial_spot_hits(rx, focus_over_efl: float, shares) -> list:
    """Real-ray spots of the lens ``rx`` (a ``synth.lens.prescription`` Prescription) focused at
    ``focus_over_efl`` focal lengths (its sensor at the real best focus): for each share of that
    distance, the hits' positions (mm) across an edge on the sensor, of rays that fill the
    entrance pupil and more (the stop cuts the beam)."""
    from synth.lens.focus import axial_rays, best_focus_image_z, disk_grid
    from synth.lens.prescription import paraxial, trace

    para = paraxial(rx)
    z_ep = para.entrance_pupil_z_mm
    focus = focus_over_efl * para.efl_mm
    z_sensor = best_focus_image_z(rx, z_ep - focus)
    u, v = disk_grid(301)
    reach = 0.75 * para.entrance_pupil_diameter_mm
    out = []
    for share in shares:
        origin, direction = axial_rays(z_ep, z_ep - share * focus, u * reach, v * reach)
        (px, _, pz), (dx, _, dz), passed, _ = trace(rx, origin, direction)
        out.append((px + (z_sensor - pz) / dz * dx)[passed])
    return out


def optiland_petzval():
    """optiland's f/1.4 Petzval (its sample library) as a prescription at its own f-number."""
    import warnings

    from lensfit.bench.designs import from_optiland

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import optiland.samples.objectives as objectives

        rx, f_number = from_optiland(objectives.PetzvalLens())
    return rx.with_f_number(f_number)


def exact_edge(across_px, noise: float, seed: int, size=(120, 160), angle_deg: float = 4.0, marker=None):
    """An edge image (0.1 dark to 0.8 light) blurred by the spot whose hits lie at ``across_px``
    across it, averaged over 8 x 8 points of each pixel, with Gaussian noise: (image, its normal
    towards the light side, its centre). ``marker``: (gap, width) px of a dark band that far
    beyond the edge on the light side (a ChArUco marker's border), light again beyond it."""
    import math

    import numpy as np

    hits = np.sort(np.asarray(across_px) - np.mean(across_px))
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    a = math.radians(angle_deg)
    normal = np.array([math.cos(a), -math.sin(a)])
    centre = np.array([w / 2, h / 2])
    light = np.zeros((h, w))
    k = 8

    def spread(t):
        return np.searchsorted(hits, t.ravel()).reshape(h, w) / len(hits)

    for i in range(k):
        for j in range(k):
            t = (xx + (i + 0.5) / k - 0.5 - centre[0]) * normal[0] + (yy + (j + 0.5) / k - 0.5 - centre[1]) * normal[1]
            light += spread(t)
            if marker is not None:
                light += spread(t - marker[0] - marker[1]) - spread(t - marker[0])
    image = 0.1 + 0.7 * light / k**2 + noise * np.random.default_rng(seed).standard_normal((h, w))
    return image, normal, centre


def disk_hits(radius_px: float, rng, n: int = 200_000):
    """Hits across an edge (px) of a uniform disk of ``radius_px``: a thin lens's spot."""
    import numpy as np

    r = radius_px * np.sqrt(rng.random(n))
    return r * np.cos(2 * np.pi * rng.random(r.size))


def jpeg_with_exif(path: Path, *, make="Canon", model="Canon EOS R5", focal=50.0, fnum=2.8, subject_m=None,
                   plane_res=None, plane_unit=None, exif_width=None, size=(48, 64), max_aperture_apex=None,
                   lens_spec=None) -> Path:
    """A small JPEG whose EXIF is written tag by tag with Pillow (not with synth.exif)."""
    import numpy as np
    from PIL import Image
    from PIL.ExifTags import IFD
    from PIL.TiffImagePlugin import IFDRational

    ex = Image.Exif()
    ex[0x010F], ex[0x0110] = make, model
    sub = ex.get_ifd(IFD.Exif)
    sub[0x920A] = IFDRational(int(focal * 10), 10)
    sub[0x829D] = IFDRational(int(fnum * 10), 10)
    if subject_m is not None:
        sub[0x9206] = IFDRational(int(subject_m * 100), 100)
    if plane_res is not None:
        sub[0xA20E] = IFDRational(int(plane_res * 1000), 1000)
        sub[0xA210] = plane_unit
    if exif_width is not None:
        sub[0xA002] = exif_width
    if max_aperture_apex is not None:  # MaxApertureValue
        sub[0x9205] = IFDRational(int(max_aperture_apex * 1000), 1000)
    if lens_spec is not None:  # LensSpecification: focal lengths and their widest f-numbers
        sub[0xA432] = tuple(IFDRational(int(v * 10), 10) for v in lens_spec)
    Image.fromarray(np.full(size, 128, np.uint8)).save(path, "JPEG", exif=ex)
    return path
