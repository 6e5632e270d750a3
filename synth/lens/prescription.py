"""Prescriptions, their paraxial data (y-nu) and exact real-ray tracing (``synth.lens``)."""


from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lensfit.optics.checks import namespace



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


def ynu(rx: Prescription, y: float, nu: float, start: int = 0, stop: int | None = None) -> tuple[float, float]:
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
    y, nu = ynu(rx, 1.0, 0.0)
    efl = -1.0 / nu  # image space is air
    bfl = -y / nu
    rear_focal = z[last] + bfl
    rear_principal = rear_focal - efl
    # Front: the reversed system (a ray parallel to the axis from the sensor side).
    rev = reverse(rx)
    yb, nub = ynu(rev, 1.0, 0.0)
    ffl = -yb / nub  # first vertex to the front focal point, measured towards the object
    front_focal = -ffl
    front_principal = front_focal + efl
    # Pupils: the chief ray crosses the axis at the stop. Rays with unit y and zero angle, and zero y
    # and unit angle, at the first vertex, carried to the stop, give the linear map to solve.
    k = rx.stop_index
    z_stop = z[k]

    def at_stop(y0, u0):
        y1, nu1 = ynu(rx, y0, u0, 0, k) if k > 0 else (y0, u0)
        n_k = rx.indices_before()[k]
        return y1 + (z_stop - z[k - 1]) * nu1 / n_k if k > 0 else y0

    a, b = at_stop(1.0, 0.0), at_stop(0.0, 1.0)
    # Chief ray: y0 = -b/a per unit object-space angle; it crosses the axis where y0 + z u = 0.
    y0 = -b / a
    entrance_z = -y0  # z of the axis crossing in object space (u = 1)
    stop_radius = rx.surfaces[k].semi_aperture_mm
    epd = 2.0 * stop_radius / abs(a)  # marginal ray from infinity: height h at z = 0 reaches a*h at the stop
    # Exit pupil: the same chief ray in image space.
    yc, nuc = ynu(rx, y0, 1.0)
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


def trace(rx: Prescription, origin, direction, *, n_image: float = 1.0):
    """Exact sequential trace of rays through every surface, front to back.

    Parameters
    ----------
    rx : the prescription (the reversed one, :func:`reverse`, traces from the sensor side)
    origin : (x, y, z) arrays, mm, points on the rays in front of the first surface (z from its
        vertex)
    direction : (dx, dy, dz) arrays, unit vectors with dz > 0

    Returns
    -------
    (x, y, z), (dx, dy, dz), passed, heights: the rays after the last surface (on it), whether
    each passed every clear aperture without total internal reflection, and the (x, y) at every
    surface (a list).
    """
    x, y, z = origin
    dx, dy, dz = direction
    xp = namespace(*origin, *direction)  # numpy or jax.numpy, as the rays
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
