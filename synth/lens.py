"""Compound lenses: a prescription (a table of spherical surfaces), its paraxial data and exact
sequential ray tracing.

A prescription lists surfaces front (object side) to back, each with

============== ===== ========================================================================
field          unit  meaning
============== ===== ========================================================================
radius_mm      mm    radius of curvature, > 0: centre of curvature behind the surface; "inf":
                     flat (the aperture stop is usually a flat, glassless surface)
thickness_mm   mm    axial distance to the next surface (the last one's is ignored: the sensor
                     position follows from the focus)
n                    refractive index after the surface at the d line (587.56 nm); 1 = air
V                    Abbe number of that glass (dispersion; optional)
glass                a glass of ``data_specs/glasses.toml`` (its Sellmeier dispersion; optional;
                     n defaults to the glass's n_d)
semi_aperture  mm    clear radius: rays outside it are blocked (this is where cat's-eye
_mm                  vignetting comes from)
stop                 the aperture stop (exactly one surface); its radius sets the f-number
============== ===== ========================================================================

Dispersion (spectral rendering, ``[lens] wavelengths_nm``): a surface with ``glass`` follows
that glass's Sellmeier equation, shifted so that its index at the d line is ``n``; one with only
``V`` follows the two-term Cauchy law ``n(lambda) = a + b / lambda^2`` through ``n`` at the d line
and ``n_F - n_C = (n - 1) / V`` (F 486.13 nm, C 656.27 nm): exact at d, F and C; from 420 to
700 nm within 2e-4 of the catalogue's crowns but up to 4e-3 off dense flints (N-SF11: the
Cauchy law misses their steep blue dispersion), so name the glass where it is known
(tests/test_spectral.py measures this).
A glass with neither cannot be traced at another wavelength. The table's n, and so the EFL,
f-number and focus, are those of the d line, the reference wavelength of every spectral render.

Coordinates: the optical axis is z, light travels towards +z (from the object to the sensor);
the first surface's vertex is at z = 0. Distances the user sees (the object and focus
distances) are measured from the entrance pupil, the point a pinhole calibration finds.

Paraxial data (:func:`paraxial`) come from the y-nu trace (W. J. Smith, Modern Optical
Engineering, ch. 2-3): refraction ``n' u' = n u - y (n' - n) / R``, transfer ``y' = y + t u'``.
Real rays (:func:`trace`) intersect each sphere exactly and refract by the vector form of
Snell's law; a ray outside a clear aperture or totally reflected is blocked. The same function
runs on NumPy (float64, for analysis and tests) and inside JAX (for rendering).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from lensfit.errors import SpecError


#: Fraunhofer lines (nm): d (helium, the reference of n and V), F and C (hydrogen).
D_LINE_NM, F_LINE_NM, C_LINE_NM = 587.5618, 486.1327, 656.2725


@dataclass(frozen=True)
class Glass:
    """An optical glass by its Sellmeier equation
    ``n^2 = 1 + sum_i B_i lambda^2 / (lambda^2 - C_i)`` (lambda in micrometres, C_i in um^2),
    the form glass makers publish (SCHOTT optical glass data sheets)."""

    name: str
    sellmeier_b: tuple[float, float, float]
    sellmeier_c_um2: tuple[float, float, float]
    source: str = ""

    def index(self, wavelength_nm):
        l2 = (np.asarray(wavelength_nm, np.float64) * 1e-3) ** 2
        return np.sqrt(1.0 + sum(b * l2 / (l2 - c) for b, c in zip(self.sellmeier_b, self.sellmeier_c_um2)))

    @property
    def nd(self) -> float:
        return float(self.index(D_LINE_NM))

    @property
    def abbe(self) -> float:
        """V_d = (n_d - 1) / (n_F - n_C)."""
        return (self.nd - 1.0) / float(self.index(F_LINE_NM) - self.index(C_LINE_NM))


def abbe_index(nd: float, abbe: float, wavelength_nm):
    """Index at ``wavelength_nm`` of a glass known by n_d and V_d: the two-term Cauchy law
    ``a + b / lambda^2`` through n_d with ``n_F - n_C = (n_d - 1) / V_d``."""
    b = (nd - 1.0) / abbe / (F_LINE_NM ** -2 - C_LINE_NM ** -2)
    return nd + b * (np.asarray(wavelength_nm, np.float64) ** -2 - D_LINE_NM ** -2)


@dataclass(frozen=True)
class Surface:
    """One refracting surface (or the stop) of a prescription; see the module notes."""

    radius_mm: float
    thickness_mm: float
    n: float
    semi_aperture_mm: float
    stop: bool = False
    abbe: float | None = None
    glass: Glass | None = None

    @property
    def curvature_per_mm(self) -> float:
        return 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm

    @property
    def dispersive(self) -> bool:
        """Whether the index after this surface is known at every wavelength (air, a glass or V)."""
        return self.n == 1.0 or self.glass is not None or self.abbe is not None

    def index_at(self, wavelength_nm: float) -> float:
        """Index after the surface at ``wavelength_nm`` (see the module notes: Dispersion)."""
        if self.glass is not None:
            return float(self.n + self.glass.index(wavelength_nm) - self.glass.index(D_LINE_NM))
        if self.abbe is not None:
            return float(abbe_index(self.n, self.abbe, wavelength_nm))
        if self.n == 1.0:
            return 1.0
        raise ValueError(f"no dispersion (V or glass) for n = {self.n}")


@dataclass(frozen=True)
class Prescription:
    """A compound lens: surfaces front to back (see the module notes)."""

    name: str
    surfaces: tuple[Surface, ...]
    source: str = ""
    design_f_number: float | None = None
    wavelength_nm: float = D_LINE_NM

    @property
    def stop_index(self) -> int:
        return next(i for i, s in enumerate(self.surfaces) if s.stop)

    def vertices_mm(self) -> np.ndarray:
        """z of each surface's vertex (the first at 0)."""
        t = np.array([s.thickness_mm for s in self.surfaces[:-1]])
        return np.concatenate([[0.0], np.cumsum(t)])

    def indices_before(self) -> np.ndarray:
        """Refractive index in front of each surface (air before the first)."""
        return np.array([1.0] + [s.n for s in self.surfaces[:-1]])

    def with_stop_radius(self, radius_mm: float) -> "Prescription":
        i = self.stop_index
        surfaces = list(self.surfaces)
        surfaces[i] = replace(surfaces[i], semi_aperture_mm=float(radius_mm))
        return replace(self, surfaces=tuple(surfaces))

    def undispersed_surfaces(self) -> list[int]:
        """Indices of glass surfaces whose dispersion is unknown (no V, no glass)."""
        return [i for i, s in enumerate(self.surfaces) if not s.dispersive]

    def at_wavelength(self, wavelength_nm: float) -> "Prescription":
        """The same lens with every index at ``wavelength_nm`` (the table is at the d line).

        Raises ValueError where a glass's dispersion is unknown (:meth:`undispersed_surfaces`)."""
        if self.wavelength_nm != D_LINE_NM:
            raise ValueError(f"{self.name} is already evaluated at {self.wavelength_nm} nm")
        if wavelength_nm == D_LINE_NM:
            return self
        missing = self.undispersed_surfaces()
        if missing:
            raise ValueError(f"{self.name}: surface[{missing[0]}] (n = {self.surfaces[missing[0]].n}) has no V or "
                             "glass, so its index at other wavelengths is unknown")
        return replace(self, wavelength_nm=float(wavelength_nm),
                       surfaces=tuple(replace(s, n=s.index_at(wavelength_nm), abbe=None, glass=None)
                                      for s in self.surfaces))

    def with_f_number(self, f_number: float) -> "Prescription":
        """The stop opened or closed so that EFL / entrance-pupil diameter = ``f_number``.

        The entrance pupil scales linearly with the stop radius (paraxially), so one step is exact.
        """
        para = paraxial(self)
        scale = (para.efl_mm / f_number) / para.entrance_pupil_diameter_mm
        return self.with_stop_radius(self.surfaces[self.stop_index].semi_aperture_mm * scale)


@dataclass(frozen=True)
class Paraxial:
    """First-order data of a prescription (mm; z from the first vertex, +z towards the sensor).

    ``efl_mm``: effective focal length; ``bfl_mm``: last vertex to the rear focal point;
    ``front_principal_z_mm``/``rear_principal_z_mm``: principal planes; entrance and exit pupils:
    position and diameter (the stop seen from the object and from the sensor);
    ``pupil_magnification``: exit / entrance pupil diameter (P).
    """

    efl_mm: float
    bfl_mm: float
    front_focal_z_mm: float
    rear_focal_z_mm: float
    front_principal_z_mm: float
    rear_principal_z_mm: float
    entrance_pupil_z_mm: float
    entrance_pupil_diameter_mm: float
    exit_pupil_z_mm: float
    exit_pupil_diameter_mm: float

    @property
    def pupil_magnification(self) -> float:
        return self.exit_pupil_diameter_mm / self.entrance_pupil_diameter_mm

    @property
    def f_number(self) -> float:
        return self.efl_mm / self.entrance_pupil_diameter_mm

    def to_json_dict(self) -> dict[str, float]:
        out = {k: float(v) for k, v in self.__dict__.items()}
        out["pupil_magnification"] = float(self.pupil_magnification)
        out["f_number"] = float(self.f_number)
        return out


def _ynu(rx: Prescription, y: float, nu: float, start: int = 0, stop: int | None = None) -> tuple[float, float]:
    """Paraxial ray (height ``y`` at surface ``start``, reduced angle ``n u`` before it) through
    surfaces ``start`` .. ``stop - 1``; returns (y, n u) just after the last refraction, at its vertex."""
    surfaces = rx.surfaces
    stop = len(surfaces) if stop is None else stop
    n_before = rx.indices_before()
    for i in range(start, stop):
        s = surfaces[i]
        nu = nu - y * (s.n - n_before[i]) * s.curvature_per_mm
        if i < stop - 1:
            y = y + s.thickness_mm * nu / s.n
    return y, nu


def paraxial(rx: Prescription) -> Paraxial:
    """Effective focal length, focal and principal planes and pupils by paraxial (y-nu) tracing."""
    z = rx.vertices_mm()
    last = len(rx.surfaces) - 1
    # Rear: a ray parallel to the axis from the object side.
    y, nu = _ynu(rx, 1.0, 0.0)
    efl = -1.0 / nu  # image space is air
    bfl = -y / nu
    rear_focal = z[last] + bfl
    rear_principal = rear_focal - efl
    # Front: the reversed system (a ray parallel to the axis from the sensor side).
    rev = reverse(rx)
    yb, nub = _ynu(rev, 1.0, 0.0)
    ffl = -yb / nub  # first vertex to the front focal point, measured towards the object
    front_focal = -ffl
    front_principal = front_focal + efl
    # Pupils: the chief ray crosses the axis at the stop. Rays with unit y and zero angle, and zero y
    # and unit angle, at the first vertex, carried to the stop, give the linear map to solve.
    k = rx.stop_index
    z_stop = z[k]

    def at_stop(y0, u0):
        y1, nu1 = _ynu(rx, y0, u0, 0, k) if k > 0 else (y0, u0)
        n_k = rx.indices_before()[k]
        return y1 + (z_stop - z[k - 1]) * nu1 / n_k if k > 0 else y0

    a, b = at_stop(1.0, 0.0), at_stop(0.0, 1.0)
    # Chief ray: y0 = -b/a per unit object-space angle; it crosses the axis where y0 + z u = 0.
    y0 = -b / a
    entrance_z = -y0  # z of the axis crossing in object space (u = 1)
    stop_radius = rx.surfaces[k].semi_aperture_mm
    epd = 2.0 * stop_radius / abs(a)  # marginal ray from infinity: height h at z = 0 reaches a*h at the stop
    # Exit pupil: the same chief ray in image space.
    yc, nuc = _ynu(rx, y0, 1.0)
    exit_z = z[last] - yc / nuc
    p_mag = 1.0 / nuc  # angular magnification of the pupils is u'/u = nuc; P = u / u'
    return Paraxial(efl, bfl, front_focal, rear_focal, front_principal, rear_principal, entrance_z, epd, exit_z,
                    abs(p_mag) * epd)


def reverse(rx: Prescription) -> Prescription:
    """The same lens traversed from the sensor side: surfaces in reverse order, radii negated,
    each index the one in front of the surface in the original (z measured the other way)."""
    s = rx.surfaces
    n_before = rx.indices_before()
    out = []
    for i in range(len(s) - 1, -1, -1):
        out.append(Surface(-s[i].radius_mm, s[i - 1].thickness_mm if i > 0 else 0.0, float(n_before[i]),
                           s[i].semi_aperture_mm, s[i].stop, s[i - 1].abbe if i > 0 else None,
                           s[i - 1].glass if i > 0 else None))
    return replace(rx, surfaces=tuple(out))


def trace(rx: Prescription, origin, direction, xp=np, *, n_image: float = 1.0):
    """Exact sequential trace of rays through every surface, front to back.

    Parameters
    ----------
    rx : the prescription (the reversed one, :func:`reverse`, traces from the sensor side)
    origin : (x, y, z) arrays, mm, points on the rays in front of the first surface (z from its
        vertex)
    direction : (dx, dy, dz) arrays, unit vectors with dz > 0
    xp : numpy or jax.numpy

    Returns
    -------
    (x, y, z), (dx, dy, dz), passed, heights: the rays after the last surface (on it), whether
    each passed every clear aperture without total internal reflection, and the (x, y) at every
    surface (a list).
    """
    x, y, z = origin
    dx, dy, dz = direction
    z_v = rx.vertices_mm()
    n_before = rx.indices_before()
    passed = xp.ones_like(x, dtype=bool)
    heights = []
    for i, s in enumerate(rx.surfaces):
        zv = float(z_v[i])
        c = s.curvature_per_mm
        if c == 0.0:
            t = (zv - z) / dz
        else:
            # |p + t d - centre| = |R|, centre on the axis at zv + R: solve the quadratic, take the root
            # nearest the vertex (the one on the hemisphere facing the incoming ray).
            R = s.radius_mm
            oz = z - (zv + R)
            b = x * dx + y * dy + oz * dz
            cc = x * x + y * y + oz * oz - R * R
            disc = b * b - cc
            passed = passed & (disc >= 0)
            root = xp.sqrt(xp.maximum(disc, 0.0))
            t = xp.where(R > 0, -b - root, -b + root)
        x, y, z = x + t * dx, y + t * dy, z + t * dz
        passed = passed & (x * x + y * y <= s.semi_aperture_mm ** 2)
        heights.append((x, y))
        n1, n2 = float(n_before[i]), float(s.n)
        if n1 != n2:
            # Surface normal towards +z side... use the unit normal pointing against the incoming ray.
            if c == 0.0:
                nx, ny, nz = xp.zeros_like(x), xp.zeros_like(x), xp.ones_like(x)
            else:
                nx, ny, nz = -x * c, -y * c, 1.0 - (z - zv) * c  # (centre - p) / R, oriented to +z
            cos_i = nx * dx + ny * dy + nz * dz
            sgn = xp.where(cos_i < 0, -1.0, 1.0)
            nx, ny, nz, cos_i = nx * sgn, ny * sgn, nz * sgn, cos_i * sgn  # now cos_i >= 0
            mu = n1 / n2
            k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
            passed = passed & (k >= 0)
            cos_t = xp.sqrt(xp.maximum(k, 0.0))
            g = cos_t - mu * cos_i
            dx, dy, dz = mu * dx + g * nx, mu * dy + g * ny, mu * dz + g * nz
    return (x, y, z), (dx, dy, dz), passed, heights


# --------------------------------------------------------------------------- files


def lens_dir() -> Path:
    from lensfit.specs import specs_dir

    return specs_dir() / "lenses"


def list_prescriptions() -> list[str]:
    return sorted(p.stem for p in lens_dir().glob("*.toml"))


def prescription_from_dict(data: dict[str, Any], path: str | Path = "<lens>") -> Prescription:
    """A prescription from its table (a lens file, or an inline ``[lens] surface = [...]``)."""
    rows = data.get("surface")
    if not isinstance(rows, list) or len(rows) < 2:
        raise SpecError(path, "surface", "needs a list of at least two surfaces, front to back")
    surfaces = []
    for i, r in enumerate(rows):
        where = f"surface[{i}]"
        if not isinstance(r, dict):
            raise SpecError(path, where, "must be a table with radius_mm, thickness_mm, n, semi_aperture_mm")
        unknown = set(r) - {"radius_mm", "thickness_mm", "n", "V", "glass", "semi_aperture_mm", "stop"}
        if unknown:
            raise SpecError(path, f"{where}.{sorted(unknown)[0]}", "unknown field; valid: radius_mm, thickness_mm, "
                            "n, V, glass, semi_aperture_mm, stop")
        glass = None
        if "glass" in r:
            glass = _glass(r["glass"], path, f"{where}.glass")
            if "V" in r:
                raise SpecError(path, f"{where}.V", "conflicts with glass (whose dispersion it is); remove one")
            if "n" not in r:
                r = {**r, "n": round(glass.nd, 6)}
            elif isinstance(r["n"], (int, float)) and abs(r["n"] - glass.nd) > 1e-3:
                raise SpecError(path, f"{where}.n", f"got {r['n']}: {glass.name} has n_d {glass.nd:.5f}; give that "
                                "index or drop n")
        for name in ("radius_mm", "thickness_mm", "n", "semi_aperture_mm"):
            if name not in r:
                raise SpecError(path, f"{where}.{name}", "is required but missing")
        radius = math.inf if r["radius_mm"] in ("inf", "-inf") else r["radius_mm"]
        if not isinstance(radius, (int, float)) or radius == 0 or not math.isfinite(abs(radius) if radius != math.inf
                                                                                    else 1.0):
            raise SpecError(path, f"{where}.radius_mm", f"got {r['radius_mm']!r}: a non-zero number of mm or \"inf\"")
        checks = (("thickness_mm", r["thickness_mm"], 0.0, 1e5), ("n", r["n"], 1.0, 4.0),
                  ("semi_aperture_mm", r["semi_aperture_mm"], 1e-6, 1e4))
        for name, v, lo, hi in checks:
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not (math.isfinite(v) and lo <= v <= hi):
                raise SpecError(path, f"{where}.{name}", f"got {v!r}: must be a number from {lo:g} to {hi:g}")
        if math.isfinite(radius) and abs(radius) < r["semi_aperture_mm"]:
            raise SpecError(path, f"{where}.semi_aperture_mm", f"got {r['semi_aperture_mm']}: larger than the "
                            f"radius of curvature ({radius}); no sphere is that wide")
        abbe = r.get("V")
        if abbe is not None and not (isinstance(abbe, (int, float)) and 10 <= abbe <= 120):
            raise SpecError(path, f"{where}.V", f"got {abbe!r}: an Abbe number from 10 to 120")
        surfaces.append(Surface(float(radius), float(r["thickness_mm"]), float(r["n"]), float(r["semi_aperture_mm"]),
                                bool(r.get("stop", False)), None if abbe is None else float(abbe), glass))
    stops = [i for i, s in enumerate(surfaces) if s.stop]
    if len(stops) != 1:
        raise SpecError(path, "surface", f"exactly one surface must have stop = true, found {len(stops)}")
    if surfaces[-1].n != 1.0:
        raise SpecError(path, f"surface[{len(surfaces) - 1}].n", "the last surface must leave the lens into air (n = 1)")
    rx = Prescription(str(data.get("name", Path(str(path)).stem)), tuple(surfaces), str(data.get("source", "")),
                      data.get("design_f_number"))
    para = paraxial(rx)
    if not (math.isfinite(para.efl_mm) and para.efl_mm > 0):
        raise SpecError(path, "surface", f"the lens has no positive focal length (EFL {para.efl_mm:.4g} mm); "
                        "check the signs of the radii (> 0: centre of curvature behind the surface)")
    return rx


@functools.cache
def glass_catalogue() -> dict[str, Glass]:
    """The glasses of ``data_specs/glasses.toml`` by name."""
    from lensfit.specs import load_toml, specs_dir

    return {name: Glass(name, tuple(g["B"]), tuple(g["C_um2"]), "SCHOTT Zemax catalogue 2017-01-20b")
            for name, g in load_toml(specs_dir() / "glasses.toml")["glass"].items()}


def _glass(name, path, where: str) -> Glass:
    catalogue = glass_catalogue()
    if not isinstance(name, str) or name not in catalogue:
        import difflib

        close = difflib.get_close_matches(str(name).upper(), list(catalogue), n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise SpecError(path, where, f"got {name!r}: not in data_specs/glasses.toml; {hint}known: "
                        f"{', '.join(sorted(catalogue))} (or give n and V)")
    return catalogue[name]


def load_prescription(name: str | Path) -> Prescription:
    """A shipped design by name (``data_specs/lenses/NAME.toml``) or the path of a lens file."""
    from lensfit.specs import load_toml

    path = Path(name)
    if path.suffix != ".toml":
        path = lens_dir() / f"{name}.toml"
        if not path.is_file():
            raise SpecError("lens.prescription", "", f"got {name!r}: no such design; shipped: "
                            f"{', '.join(list_prescriptions())} (or the path of a lens .toml)")
    return prescription_from_dict(load_toml(path), path)


def image_z(rx: Prescription, object_z_mm: float) -> float:
    """z of the paraxial image of the axial point at ``object_z_mm`` (lens coordinates; -inf:
    an object at infinity, whose image is the rear focal point)."""
    if math.isinf(object_z_mm):
        y, nu = _ynu(rx, 1.0, 0.0)
    else:
        y, nu = _ynu(rx, -object_z_mm, 1.0)  # unit angle from the object point to the first vertex
    return float(rx.vertices_mm()[-1] - y / nu)


def object_z(rx: Prescription, image_z_mm: float) -> float:
    """z of the axial object point whose paraxial image lies at ``image_z_mm`` (the inverse of
    :func:`image_z`; -inf when that is the rear focal point)."""
    last = float(rx.vertices_mm()[-1])
    rev = reverse(rx)
    y, nu = _ynu(rev, -(last - image_z_mm), 1.0)
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
