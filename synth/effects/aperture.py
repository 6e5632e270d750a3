"""``aperture``: the shape of the lens opening, and so the shape of the bokeh.

Model
-----
A defocused point spreads into a scaled copy of the aperture (thin lens, geometric optics):
the blur spot has the aperture's shape, scaled by ``C / A`` where ``C = A s |1/D_s - 1/z|``.

=================  =====================================================  ===========
shape              parameters                                             size
=================  =====================================================  ===========
``circle``         (none; the default)                                    diameter A = f/N
``polygon``        ``blades`` (3-32), ``rotation_deg`` (first vertex,     vertices on the circle
                   counter-clockwise from +x in the stored image)         of diameter A
``anamorphic``     ``squeeze`` (> 0; 1.33, 1.5, 2 are common)            ellipse: vertical
                                                                          diameter A, horizontal
                                                                          A / squeeze
=================  =====================================================  ===========

Orientation: the lens-plane axes are the stored image's (x right, y down), and a point behind
the plane of focus spreads into the aperture as drawn; in front of it the rays have not yet
crossed at the sensor, and the stored (re-inverted) image shows the shape turned by 180
degrees. ``rotation_deg`` therefore describes background bokeh.

So ``f_number`` always names the vertical extent (for the polygon, the circumscribed circle);
a regular polygon's area is ``n/(2 pi) sin(2 pi/n)`` of its circle's, an ellipse's ``1/squeeze``,
and exposure scales with that area (truth.json records ``area_fraction``). The anamorphic
ellipse is the bokeh of a desqueezed anamorphic image: taller than wide by the squeeze ratio.

Both render methods use it: ``raytrace`` samples lens points uniformly over the shape
(``sample``: stratified unit square -> shape), ``convolve`` convolves with the shape
rasterised at the blur's size (``kernel``: area of the shape in each cell to 1/oversample^2).

Reference: Pharr, Jakob & Humphreys, *Physically Based Rendering*, 4th ed., sec. 5.2.3 (thin
lens) and A.5 (sampling shapes); Turk, "Generating random points in triangles", Graphics
Gems (1990).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NAME = "aperture"


@dataclass(frozen=True)
class Aperture:
    """A lens opening. ``shape`` is circle, polygon or anamorphic; units: degrees, ratio."""

    shape: str = "circle"
    blades: int = 0
    rotation_deg: float = 0.0
    squeeze: float = 1.0

    @classmethod
    def from_spec(cls, spec: dict) -> "Aperture":
        shape = spec.get("shape", "circle")
        if shape == "polygon":
            return cls("polygon", blades=int(spec["blades"]), rotation_deg=float(spec.get("rotation_deg", 0.0)))
        if shape == "anamorphic":
            return cls("anamorphic", squeeze=float(spec["squeeze"]))
        return cls()

    @property
    def static(self) -> tuple:
        """Hashable description for compiled kernels."""
        if self.shape == "polygon":
            return ("polygon", self.blades, self.rotation_deg)
        if self.shape == "anamorphic":
            return ("anamorphic", self.squeeze)
        return ("circle",)

    @property
    def area_fraction(self) -> float:
        """Area relative to the circle of diameter A."""
        if self.shape == "polygon":
            n = self.blades
            return n / (2 * math.pi) * math.sin(2 * math.pi / n)
        if self.shape == "anamorphic":
            return 1.0 / self.squeeze
        return 1.0

    @property
    def extent(self) -> float:
        """Largest distance of the shape from its centre, in units of the radius A/2."""
        return max(1.0, 1.0 / self.squeeze) if self.shape == "anamorphic" else 1.0

    def vertices(self) -> np.ndarray:
        """Polygon vertices (n, 2) on the unit-radius circle, image axes (x right, y down)."""
        n = self.blades
        ang = math.radians(self.rotation_deg) + 2 * math.pi * np.arange(n) / n
        # counter-clockwise as seen in the image (y down): negate y.
        return np.stack([np.cos(ang), -np.sin(ang)], axis=-1)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether points (in units of the radius A/2) lie inside the shape."""
        if self.shape == "anamorphic":
            return (x * self.squeeze) ** 2 + y**2 <= 1.0
        if self.shape == "polygon":
            v = self.vertices()
            inside = np.ones(np.broadcast(x, y).shape, bool)
            for k in range(len(v)):
                a, b = v[k], v[(k + 1) % len(v)]
                # the centre is inside; keep points on the same side of every edge
                cross_c = (b[0] - a[0]) * (0 - a[1]) - (b[1] - a[1]) * (0 - a[0])
                cross = (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0])
                inside &= cross * np.sign(cross_c) >= 0
            return inside
        return x * x + y * y <= 1.0

    def truth(self) -> dict:
        out = {"shape": self.shape, "area_fraction": self.area_fraction,
               "size": ("vertical diameter f/N, horizontal f/(N squeeze)" if self.shape == "anamorphic" else
                        "vertices on the circle of diameter f/N" if self.shape == "polygon" else "diameter f/N")}
        if self.shape == "polygon":
            out.update(blades=self.blades, rotation_deg=self.rotation_deg)
        if self.shape == "anamorphic":
            out.update(squeeze=self.squeeze)
        return out


def sample(static: tuple, u, v, disk):
    """Map stratified uniforms (u, v) in [0, 1)^2 to a uniform point of the shape (unit radius).

    ``disk(u, v)`` is the circle's mapping (the renderer's concentric map), reused for the
    circle and the ellipse so that a circular aperture stays exactly what it was.
    """
    import jax.numpy as jnp

    if static[0] == "anamorphic":
        x, y = disk(u, v)
        return x / static[1], y
    if static[0] == "polygon":
        n, rot = static[1], math.radians(static[2])
        k = jnp.floor(u * n)
        t = u * n - k  # position along the triangle's outer edge, stays stratified
        a0 = rot + 2 * math.pi * k / n
        a1 = a0 + 2 * math.pi / n
        r = jnp.sqrt(v)  # uniform over the triangle (centre, vertex k, vertex k+1)
        x = r * ((1 - t) * jnp.cos(a0) + t * jnp.cos(a1))
        y = -r * ((1 - t) * jnp.sin(a0) + t * jnp.sin(a1))
        return x, y
    return disk(u, v)


def kernel(aperture: Aperture, diameter_cells: float, oversample: int = 8) -> np.ndarray:
    """The shape of vertical diameter ``diameter_cells``, each cell holding the shape's area in it
    (to 1/oversample^2 of a cell), normalised to unit sum; odd size, centred."""
    radius = 0.5 * diameter_cells
    if radius * oversample < 0.5:
        return np.ones((1, 1))
    half = int(math.ceil(radius * aperture.extent + 0.5))
    n = 2 * half + 1
    sub = (np.arange(n * oversample) + 0.5) / oversample - n / 2  # sub-cell centres, cells
    x, y = np.meshgrid(sub / radius, sub / radius)
    inside = aperture.contains(x, y).astype(np.float64)
    k = inside.reshape(n, oversample, n, oversample).mean(axis=(1, 3))
    return k / k.sum()
