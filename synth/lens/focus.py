"""Where a compound lens focuses: paraxial conjugates, the best-focus plane (least RMS spot, one
or several wavelengths), the real entrance pupil and the fastest usable f-number."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from synth.lens.prescription import Prescription, ynu, paraxial, reverse, trace



def image_z(rx: Prescription, object_z_mm: float) -> float:
    """z of the paraxial image of the axial point at ``object_z_mm`` (lens coordinates; -inf:
    an object at infinity, whose image is the rear focal point)."""
    if math.isinf(object_z_mm):
        y, nu = ynu(rx, 1.0, 0.0)
    else:
        y, nu = ynu(rx, -object_z_mm, 1.0)  # unit angle from the object point to the first vertex
    return float(rx.vertices_mm()[-1] - y / nu)


def object_z(rx: Prescription, image_z_mm: float) -> float:
    """z of the axial object point whose paraxial image lies at ``image_z_mm`` (the inverse of
    :func:`image_z`; -inf when that is the rear focal point)."""
    last = float(rx.vertices_mm()[-1])
    rev = reverse(rx)
    y, nu = ynu(rev, -(last - image_z_mm), 1.0)
    if nu == 0.0:
        return -math.inf
    return last - float(rev.vertices_mm()[-1] - y / nu)


def axial_rays(z_ep: float, object_z_mm: float, tx: np.ndarray, ty: np.ndarray):
    """Rays from the axial object point at ``object_z_mm`` (-inf: parallel rays from infinity)
    through the points ``(tx, ty)`` of the entrance-pupil plane at ``z_ep`` (the paraxial
    ``entrance_pupil_z_mm``): (origin, direction) for :func:`trace`."""
    tx, ty = np.asarray(tx, np.float64), np.asarray(ty, np.float64)
    if math.isinf(object_z_mm):
        return (tx, ty, np.full_like(tx, min(0.0, z_ep) - 1.0)), (np.zeros_like(tx), np.zeros_like(tx),
                                                                   np.ones_like(tx))
    dz = z_ep - object_z_mm
    norm = np.sqrt(tx * tx + ty * ty + dz * dz)
    return (np.zeros_like(tx), np.zeros_like(tx), np.full_like(tx, float(object_z_mm))), (
        tx / norm, ty / norm, np.full_like(tx, dz) / norm)


def disk_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of the centres of an n x n grid over [-1, 1]^2 that lie in the unit disk: pupil
    samples, scaled by the caller to the pupil's radius."""
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    u, v = np.meshgrid(g, g)
    inside = u * u + v * v <= 1.0
    return u[inside], v[inside]


#: Pupil samples per diameter for the best-focus search (about 0.8 x this squared rays).
BEST_FOCUS_GRID = 161


def best_focus_image_z(rx: Prescription, object_z_mm: float, grid: int = BEST_FOCUS_GRID) -> float:
    """z of the plane where the real rays from the axial point at ``object_z_mm`` (-inf: at
    infinity) have the smallest RMS spot radius: the best focus of the lens as it is stopped
    down (spherical aberration moves it from the paraxial image, :func:`image_z`).

    The rays fill the entrance pupil uniformly (a square grid of ``grid`` samples across an
    overfilled pupil; the stop blocks what lies outside it). After the last surface each ray is a
    line, so its height on a plane at z is linear in z and the spot's variance is a quadratic in
    z: the minimum is closed-form. This is also the vertex of the asymptotes of the second-moment
    blur diameter versus defocus, the V a blur-versus-depth fit finds.
    """
    return polychromatic_best_focus_image_z([rx], object_z_mm, grid)


def polychromatic_best_focus_image_z(rxs: list[Prescription], object_z_mm: float,
                                     grid: int = BEST_FOCUS_GRID) -> float:
    """:func:`best_focus_image_z` of the light of several wavelengths together (``rxs``: the
    lens at each, :meth:`Prescription.at_wavelength`), each wavelength weighted equally: the
    plane where the grey image of the axial point is smallest, where autofocus on a grey image
    puts the sensor."""
    heights, slopes, weights = [], [], []
    u, v = disk_grid(grid)
    for rx in rxs:
        para = paraxial(rx)
        r = 0.5 * para.entrance_pupil_diameter_mm * 1.25
        rays = axial_rays(para.entrance_pupil_z_mm, object_z_mm, r * u, r * v)
        (x, y, z), (dx, dy, dz_out), passed, _ = trace(rx, *rays)
        ok = passed & (dz_out > 1e-9)
        if ok.sum() < 16:
            raise ValueError(f"{rx.name}: fewer than 16 rays from the axial object pass the lens; no best focus")
        x, y, z, dx, dy, dz_out = (q[ok] for q in (x, y, z, dx, dy, dz_out))
        for h, d in ((x, dx), (y, dy)):
            b = d / dz_out          # height at plane Z: (h - b z) + b Z
            heights.append(h - b * z)
            slopes.append(b)
            weights.append(np.full(b.shape, 1.0 / b.size))
    a, b, w = np.concatenate(heights), np.concatenate(slopes), np.concatenate(weights)
    w = w / w.sum()
    # Mean square spot radius at Z: sum w (a + b Z)^2 (the axial point's spot is centred on the
    # axis by symmetry): minimal at Z = -sum(w a b) / sum(w b^2).
    return float(-np.sum(w * a * b) / np.sum(w * b * b))


def axial_beam_clipped(rx: Prescription, object_z_mm: float, rings: int = 64, spokes: int = 16) -> float:
    """Fraction of the axial beam through the paraxial entrance pupil that a clear aperture
    other than the stop blocks (the stopped ``rx``; object at ``object_z_mm``, -inf: infinity):
    0 when the stop alone limits the beam, as it should at any f-number a lens is made for."""
    para = paraxial(rx)
    r = 0.5 * para.entrance_pupil_diameter_mm * np.sqrt((np.arange(rings) + 0.5) / rings)
    phi = np.arange(spokes) * (2 * math.pi / spokes)
    R, F = np.meshgrid(r, phi)
    origin, direction = axial_rays(para.entrance_pupil_z_mm, object_z_mm, (R * np.cos(F)).ravel(),
                                   (R * np.sin(F)).ravel())
    # Clear apertures opened wide except the others: what the stop alone passes vs all of them.
    k = rx.stop_index
    open_rx = replace(rx, surfaces=tuple(replace(s, semi_aperture_mm=1e9) if i != k else s
                                         for i, s in enumerate(rx.surfaces)))
    _, _, stop_only, _ = trace(open_rx, origin, direction)
    _, _, passed, _ = trace(rx, origin, direction)
    return float(1.0 - passed.sum() / max(stop_only.sum(), 1))


def fastest_f_number(rx: Prescription, object_z_mm: float, tolerance: float = 0.01) -> float:
    """The smallest f-number at which the clear apertures other than the stop block at most
    ``tolerance`` of the axial beam from ``object_z_mm`` (bisection on log N, 1 % steps)."""
    lo, hi = math.log(0.5), math.log(64.0)
    if axial_beam_clipped(rx.with_f_number(math.exp(hi)), object_z_mm) > tolerance:
        return math.inf
    while hi - lo > 0.005:
        mid = 0.5 * (lo + hi)
        if axial_beam_clipped(rx.with_f_number(math.exp(mid)), object_z_mm) > tolerance:
            lo = mid
        else:
            hi = mid
    return math.exp(hi)


def real_entrance_pupil_diameter(rx: Prescription, object_z_mm: float) -> float:
    """Diameter of the entrance pupil as real rays from the axial point at ``object_z_mm`` (-inf:
    infinity) see it: twice the largest height on the paraxial entrance-pupil plane of a ray
    that passes every clear aperture (bisection to 1e-9 relative).

    Pupil spherical aberration makes it differ from the paraxial diameter by a per cent or more
    at full aperture; the cone of light a defocused point spreads, and so the blur, follows the
    real pupil: ``EFL / real_entrance_pupil_diameter`` is the f-number blur measures.
    """
    para = paraxial(rx)

    def passes(h: float) -> bool:
        return bool(trace(rx, *axial_rays(para.entrance_pupil_z_mm, object_z_mm, np.zeros(1), np.array([h])))[2][0])

    lo, hi = 0.0, para.entrance_pupil_diameter_mm  # twice the paraxial radius: blocked
    if passes(hi):
        raise ValueError(f"{rx.name}: rays beyond twice the entrance pupil pass; no aperture limits the beam")
    while hi - lo > 1e-9 * para.entrance_pupil_diameter_mm:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if passes(mid) else (lo, mid)
    return 2.0 * lo


#: Least axial-and-edge clearance (mm) a moving focus group keeps from its neighbours.
GROUP_CLEARANCE_MM = 0.05


def _sag(radius_mm: float, h: np.ndarray) -> np.ndarray:
    """z of a spherical surface at height ``h`` from its vertex (0 where flat)."""
    if math.isinf(radius_mm):
        return np.zeros_like(h)
    return radius_mm - math.copysign(1.0, radius_mm) * np.sqrt(np.maximum(radius_mm * radius_mm - h * h, 0.0))


def _clearance(front, back, gap_mm: float) -> float:
    """Least axial distance between two neighbouring surfaces ``gap_mm`` apart on the axis, over
    the heights both clear apertures share."""
    h = np.linspace(0.0, min(front.semi_aperture_mm, back.semi_aperture_mm), 64)
    return float(np.min(gap_mm + _sag(back.radius_mm, h) - _sag(front.radius_mm, h)))


def check_focus_group(rx: Prescription, group: tuple[int, int]) -> str | None:
    """Why ``group`` (first and last surface index, inclusive) cannot move inside ``rx`` as a
    focus group, or None where it can: both indices on the lens, in order, not the whole lens
    (which is unit focusing), and air on both sides of the group."""
    first, last = group
    n = len(rx.surfaces)
    if not 0 <= first <= last < n:
        return f"surface indices first <= last from 0 to {n - 1} ({rx.name} has {n} surfaces)"
    if first == 0 and last == n - 1:
        return "a group short of the whole lens (moving every surface is unit focusing)"
    if rx.surfaces[last].n != 1.0 or (first > 0 and rx.surfaces[first - 1].n != 1.0):
        return "a group bounded by air on both sides (it may not split a cemented element or a glass)"
    return None


def shift_group(rx: Prescription, group: tuple[int, int], shift_mm: float) -> tuple[Prescription, float]:
    """``rx`` with the surfaces ``group[0]..group[1]`` moved ``shift_mm`` towards the image, the
    other surfaces and the sensor staying where they are; and how far the lens coordinates
    (first vertex at 0) moved against the fixed frame (the unshifted lens's): non-zero only where
    the group holds the first surface, which then moves, so that a fixed z is z - that in the
    shifted lens's coordinates."""
    first, last = group
    surfaces = list(rx.surfaces)
    if first > 0:
        surfaces[first - 1] = replace(surfaces[first - 1], thickness_mm=surfaces[first - 1].thickness_mm + shift_mm)
    if last < len(surfaces) - 1:
        surfaces[last] = replace(surfaces[last], thickness_mm=surfaces[last].thickness_mm - shift_mm)
    return replace(rx, surfaces=tuple(surfaces)), (shift_mm if first == 0 else 0.0)


def group_travel(rx: Prescription, group: tuple[int, int], sensor_z_mm: float) -> tuple[float, float]:
    """The shifts (mm, + towards the image) the focus group can take before it comes within
    ``GROUP_CLEARANCE_MM`` of a neighbouring surface (anywhere over their shared clear
    apertures) or, as the last group, of the sensor at ``sensor_z_mm``."""
    first, last = group
    s = rx.surfaces
    # A front group has nothing ahead of it: half the EFL forward is far beyond any close focus.
    lo = (-0.5 * paraxial(rx).efl_mm if first == 0 else
          -(_clearance(s[first - 1], s[first], s[first - 1].thickness_mm) - GROUP_CLEARANCE_MM))
    if last < len(s) - 1:
        hi = _clearance(s[last], s[last + 1], s[last].thickness_mm) - GROUP_CLEARANCE_MM
    else:
        # the last surface's rim may reach behind its vertex (a convex rear surface's does not)
        rim = float(np.max(_sag(s[last].radius_mm, np.linspace(0.0, s[last].semi_aperture_mm, 64))))
        hi = sensor_z_mm - float(rx.vertices_mm()[-1]) - max(rim, 0.0) - GROUP_CLEARANCE_MM
    return lo, hi


def internal_focus(rx: Prescription, group: tuple[int, int], focus_distance_mm: float, sensor_z_mm: float,
                   wavelengths_nm: tuple[float, ...] = (), focus_plane: str = "best",
                   steps: int = 48) -> tuple[Prescription, float]:
    """Focus ``rx`` (stopped) on ``focus_distance_mm`` (from its entrance pupil, which moves
    with the group when the stop or the glass in front of it does) by moving the focus group
    alone, the sensor fixed at ``sensor_z_mm`` (lens coordinates of ``rx``): the shifted lens and
    the shift (mm, + towards the image), the smallest one that puts the best focus (or the
    paraxial image) of the axial point at that distance on the sensor.

    Raises ValueError where no shift within the group's travel (:func:`group_travel`) does."""
    rxs = [rx.at_wavelength(w) for w in wavelengths_nm] if wavelengths_nm else [rx]

    def miss(shift: float, grid: int = BEST_FOCUS_GRID) -> float:
        moved = [shift_group(r, group, shift) for r in rxs]
        shifted, moved_by = moved[0]
        z_obj = paraxial(shifted).entrance_pupil_z_mm - focus_distance_mm
        if focus_plane == "best":
            z_img = polychromatic_best_focus_image_z([m for m, _ in moved], z_obj, grid)
        else:
            z_img = image_z(shifted, z_obj)
        return z_img - (sensor_z_mm - moved_by)

    lo, hi = group_travel(rx, group, sensor_z_mm)
    if not lo < hi:
        raise ValueError(f"the focus group (surfaces {group[0]}-{group[1]}) has no room to move")
    # Coarse grid first (a smaller pupil grid): the sign change nearest the design position.
    grid = np.unique(np.concatenate([np.linspace(lo, hi, steps), [0.0]]))
    grid = grid[(grid >= lo) & (grid <= hi)]
    values = []
    for s in grid:
        try:
            with np.errstate(over="ignore", invalid="ignore"):  # rays lost at a far position: blocked
                values.append(miss(float(s), 41))
        except ValueError:  # rays cut off at this position: no focus there
            values.append(math.nan)
    values = np.asarray(values)
    brackets = [(grid[i], grid[i + 1]) for i in range(len(grid) - 1)
                if np.isfinite(values[i]) and np.isfinite(values[i + 1]) and values[i] * values[i + 1] <= 0.0]
    if not brackets:
        raise ValueError(f"moving the focus group (surfaces {group[0]}-{group[1]}) from {lo:+.2f} to {hi:+.2f} mm "
                         f"does not focus {focus_distance_mm:g} mm on the sensor")
    a, b = min(brackets, key=lambda ab: min(abs(ab[0]), abs(ab[1])))
    from scipy.optimize import brentq

    fa, fb = miss(float(a)), miss(float(b))
    if fa * fb > 0.0:  # the fine pupil grid moved the root a little: widen by one step each way
        step = (hi - lo) / steps
        a, b = max(lo, a - step), min(hi, b + step)
        fa, fb = miss(float(a)), miss(float(b))
        if fa * fb > 0.0:
            raise ValueError(f"the focus group's position for {focus_distance_mm:g} mm could not be bracketed")
    shift = float(brentq(miss, float(a), float(b), xtol=1e-9, rtol=1e-12))
    return shift_group(rx, group, shift)[0], shift
