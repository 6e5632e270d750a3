"""Thin-lens optics, implemented once for the whole project.

Pure, vectorised functions (anything array-like is accepted and broadcast), computed in
float64: in NumPy for Python and NumPy inputs (returning NumPy values; JAX is not imported), in
``jax.numpy`` where an input is a JAX array (then traceable, jittable, differentiable). Symbols and units follow ``data_specs/CONVENTIONS.md``: every length is in
millimetres, times in seconds, angles in degrees where the name ends in ``_deg``.

=====================  ===========================================================
symbol                 meaning
=====================  ===========================================================
``f``                  focal length
``N``                  f-number
``A = f/N``            aperture (entrance pupil) diameter
``d``                  object distance, from the lens plane
``z(d)``               image distance, from the lens plane (negative: virtual image)
``D_s``                focus distance: object-side distance in focus, from the lens
``s = z(D_s)``         sensor distance: lens plane to sensor plane
``C``                  circle-of-confusion *diameter* on the sensor
=====================  ===========================================================

"Focus distance" on a lens barrel or in EXIF is measured from the sensor plane; that is
``D_s + s`` (:func:`focus_distance_from_sensor`), a different quantity from ``D_s``.

Infinity is allowed where it is physical (an object or the focus at infinity): the formulas
are written in inverse distances so that ``1/inf = 0`` gives the correct limit, never NaN.
With concrete inputs every argument is validated and a violation raises
:class:`lensfit.errors.InputError` (a ``ValueError``) naming the argument.

References
----------
.. [1] CS184 (UC Berkeley, Summer 2020), "Cameras and Lenses" (the course notes):
   thin-lens equation, circle of confusion, depth of field, sensor sizes.
.. [2] E. Hecht, *Optics*, 5th ed., Pearson 2017, sec. 5.2 (thin lenses).
.. [3] S. F. Ray, *Applied Photographic Optics*, 3rd ed., Focal Press 2002, ch. 15 (depth of
   field) and ch. 8 (exposure).
"""

from __future__ import annotations

import math

from lensfit._checks import arg, float64, require, xp

__all__ = [
    "FULL_FRAME_DIAGONAL_MM",
    "image_distance",
    "object_distance",
    "sensor_distance",
    "focus_distance_from_sensor",
    "magnification",
    "aperture_diameter",
    "f_number",
    "coc_diameter_image_side",
    "coc_diameter_object_side",
    "coc_diameter",
    "near_limit",
    "far_limit",
    "depth_of_field",
    "depth_of_field_approx",
    "hyperfocal_distance",
    "default_coc_diameter",
    "field_of_view_deg",
    "crop_factor",
    "equivalent_focal_length_35mm",
    "exposure_value",
    "equivalent_shutter_s",
    "equivalent_f_number",
    "equivalent_iso",
]

#: Diagonal of the 36 x 24 mm ("35 mm", full-frame) format, the reference of crop factors.
FULL_FRAME_DIAGONAL_MM = float((36.0**2 + 24.0**2) ** 0.5)


# --------------------------------------------------------------------------- thin-lens equation


def _conjugate(f, x):
    # 1/f = 1/x + 1/y solved for y, written in inverses so that x = inf gives y = f.
    return 1.0 / (1.0 / f - 1.0 / x)


@float64
def image_distance(focal_length_mm, object_distance_mm):
    """Image distance from the thin-lens equation.

    .. math:: \\frac{1}{f} = \\frac{1}{d} + \\frac{1}{z}
              \\quad\\Rightarrow\\quad z = \\frac{1}{1/f - 1/d} = \\frac{f d}{d - f}

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    object_distance_mm : array_like
        Object distance d from the lens plane, mm, > 0 and != f; ``inf`` allowed.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Image distance z from the lens plane, mm. ``z > f`` for a real image (d > f),
        ``z = f`` for an object at infinity, and ``z < 0`` for an object inside the focal
        length: a *virtual* image on the object's side of the lens (a magnifier).

    Notes
    -----
    An object exactly at the focal point images at infinity; that raises
    :class:`~lensfit.errors.InputError` rather than returning ``inf``.

    Examples
    --------
    >>> float(image_distance(50.0, 2050.0))
    51.25
    >>> float(image_distance(50.0, 25.0))   # inside f: virtual image
    -50.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    d = arg("object_distance_mm", object_distance_mm, positive=True, allow_inf=True)
    require(d != f, "object_distance_mm", d, "!= focal_length_mm",
            "an object at the focal point images at infinity")
    return _conjugate(f, d)


@float64
def object_distance(focal_length_mm, image_distance_mm):
    """Object distance that images at a given image distance (thin-lens equation inverted).

    .. math:: d = \\frac{1}{1/f - 1/z} = \\frac{f z}{z - f}

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    image_distance_mm : array_like
        Image distance z from the lens plane, mm, != 0 and != f; ``inf`` allowed (gives f).
        Negative for a virtual image.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Object distance d from the lens plane, mm. Positive for every real object;
        ``0 < d < f`` when ``z < 0`` (virtual image).

    Examples
    --------
    >>> round(float(object_distance(50.0, 51.25)), 9)
    2050.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    z = arg("image_distance_mm", image_distance_mm, allow_inf=True)
    require(z != f, "image_distance_mm", z, "!= focal_length_mm",
            "an image at the focal plane comes from an object at infinity")
    require(z != 0, "image_distance_mm", z, "!= 0")
    return _conjugate(f, z)


@float64
def sensor_distance(focal_length_mm, focus_distance_mm):
    """Lens-to-sensor distance s that focuses the camera at ``focus_distance_mm``.

    .. math:: s = \\frac{f D_s}{D_s - f}

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane (object side), mm, > f; ``inf`` gives s = f.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Sensor distance s, mm, > f.

    Examples
    --------
    >>> round(float(sensor_distance(50.0, 2000.0)), 4)
    51.2821
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    D = arg("focus_distance_mm", focus_distance_mm, positive=True, allow_inf=True)
    require(D > f, "focus_distance_mm", D, "> focal_length_mm",
            "a camera can only focus on objects beyond the focal length")
    return _conjugate(f, D)


@float64
def focus_distance_from_sensor(focal_length_mm, focus_distance_mm):
    """Focus distance measured from the sensor plane (lens scale, EXIF): ``D_s + s``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane, mm, > f; ``inf`` allowed.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Distance from the sensor plane to the plane of focus, mm. At least ``4 f``
        (reached at 1:1 magnification, ``D_s = s = 2f``).

    Examples
    --------
    >>> float(focus_distance_from_sensor(50.0, 100.0))
    200.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    D = arg("focus_distance_mm", focus_distance_mm, positive=True, allow_inf=True)
    require(D > f, "focus_distance_mm", D, "> focal_length_mm")
    return D + _conjugate(f, D)


@float64
def magnification(focal_length_mm, object_distance_mm):
    """Lateral magnification of the thin lens, as in the course: ``M = z/d = f/(d - f)``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    object_distance_mm : array_like
        Object distance d from the lens plane, mm, > 0 and != f; ``inf`` gives 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        ``M > 0``: real, inverted image ``M`` times the object's size (``M = 1`` at
        ``d = 2f``). ``M < 0``: virtual, upright image ``|M|`` times the object's size
        (object inside the focal length; ``|M| > 1``).

    Examples
    --------
    >>> float(magnification(50.0, 100.0))
    1.0
    >>> float(magnification(50.0, 25.0))
    -2.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    d = arg("object_distance_mm", object_distance_mm, positive=True, allow_inf=True)
    require(d != f, "object_distance_mm", d, "!= focal_length_mm",
            "an object at the focal point images at infinity")
    # f/(d - f) written as (f/d)/(1 - f/d) so that d = inf gives 0.
    r = f / d
    return r / (1.0 - r)


# --------------------------------------------------------------------------- aperture


@float64
def aperture_diameter(focal_length_mm, f_number):
    """Aperture (entrance-pupil) diameter ``A = f/N``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    f_number : array_like
        f-number N, > 0 (the Zeiss 50 mm f/0.7 of *Barry Lyndon* is N = 0.7).

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Aperture diameter A, mm.

    Examples
    --------
    >>> float(aperture_diameter(50.0, 2.0))
    25.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    N = arg("f_number", f_number, positive=True)
    return f / N


@float64
def f_number(focal_length_mm, aperture_diameter_mm):
    """f-number ``N = f/A``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    aperture_diameter_mm : array_like
        Aperture diameter A, mm, > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        f-number N (dimensionless).

    Examples
    --------
    >>> float(f_number(50.0, 25.0))
    2.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    A = arg("aperture_diameter_mm", aperture_diameter_mm, positive=True)
    return f / A


# --------------------------------------------------------------------------- circle of confusion


@float64
def coc_diameter_image_side(aperture_diameter_mm, sensor_distance_mm, image_distance_mm):
    """Circle-of-confusion diameter from image-side distances (the course's first form).

    .. math:: C = A \\frac{|s - z|}{|z|} = A \\left| 1 - \\frac{s}{z} \\right|

    By similar triangles: the cone of light converging to (or, for a virtual image,
    diverging from) the image point at ``z`` has diameter ``A`` at the lens and ``C`` at
    the sensor plane ``s``.

    Parameters
    ----------
    aperture_diameter_mm : array_like
        Aperture diameter A, mm, > 0.
    sensor_distance_mm : array_like
        Lens-to-sensor distance s, mm, > 0.
    image_distance_mm : array_like
        Image distance z of the object point, mm, != 0; negative for a virtual image;
        ``inf`` (object at the focal point) gives ``C = A``.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        CoC diameter C on the sensor, mm (the *diameter*; the blur radius is C/2).

    Examples
    --------
    >>> round(float(coc_diameter_image_side(25.0, 51.0, 50.0)), 6)
    0.5
    """
    A = arg("aperture_diameter_mm", aperture_diameter_mm, positive=True)
    s = arg("sensor_distance_mm", sensor_distance_mm, positive=True)
    z = arg("image_distance_mm", image_distance_mm, allow_inf=True)
    require(z != 0, "image_distance_mm", z, "!= 0")
    return A * xp().abs(1.0 - s / z)


@float64
def coc_diameter_object_side(aperture_diameter_mm, sensor_distance_mm, focus_distance_mm,
                             object_distance_mm):
    """Circle-of-confusion diameter from object-side distances (the course's second form).

    .. math:: C = A s \\left| \\frac{1}{D_s} - \\frac{1}{d} \\right|

    Linear in inverse depth: a "V" with slope ``A s`` and its vertex at ``1/D_s``. Equal to
    :func:`coc_diameter_image_side` through the thin-lens equation, for real and virtual
    images alike.

    Parameters
    ----------
    aperture_diameter_mm : array_like
        Aperture diameter A, mm, > 0.
    sensor_distance_mm : array_like
        Lens-to-sensor distance s, mm, > 0.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane, mm, > 0; ``inf`` allowed.
    object_distance_mm : array_like
        Object distance d from the lens plane, mm, > 0; ``inf`` allowed.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        CoC diameter C on the sensor, mm.

    Examples
    --------
    >>> round(float(coc_diameter_object_side(25.0, 51.25, 2050.0, 1025.0)), 6)
    0.625
    """
    A = arg("aperture_diameter_mm", aperture_diameter_mm, positive=True)
    s = arg("sensor_distance_mm", sensor_distance_mm, positive=True)
    D = arg("focus_distance_mm", focus_distance_mm, positive=True, allow_inf=True)
    d = arg("object_distance_mm", object_distance_mm, positive=True, allow_inf=True)
    return A * s * xp().abs(1.0 / D - 1.0 / d)


@float64
def coc_diameter(focal_length_mm, f_number, focus_distance_mm, object_distance_mm):
    """Circle-of-confusion diameter of a lens focused at ``D_s`` for an object at ``d``.

    .. math:: C = \\frac{f}{N} \\cdot \\frac{f D_s}{D_s - f}
              \\left| \\frac{1}{D_s} - \\frac{1}{d} \\right|

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    f_number : array_like
        f-number N, > 0.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane, mm, > f; ``inf`` allowed.
    object_distance_mm : array_like
        Object distance d from the lens plane, mm, > 0; ``inf`` allowed.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        CoC diameter on the sensor, mm. Zero at ``d = D_s``; tends to ``A s / D_s`` as
        ``d -> inf``.

    Examples
    --------
    >>> round(float(coc_diameter(50.0, 2.0, 2050.0, 1025.0)), 6)
    0.625
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    N = arg("f_number", f_number, positive=True)
    D = arg("focus_distance_mm", focus_distance_mm, positive=True, allow_inf=True)
    d = arg("object_distance_mm", object_distance_mm, positive=True, allow_inf=True)
    require(D > f, "focus_distance_mm", D, "> focal_length_mm",
            "a camera can only focus on objects beyond the focal length")
    return (f / N) * _conjugate(f, D) * xp().abs(1.0 / D - 1.0 / d)


# --------------------------------------------------------------------------- depth of field


def _dof_args(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm):
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    N = arg("f_number", f_number, positive=True)
    C = arg("acceptable_coc_diameter_mm", acceptable_coc_diameter_mm, positive=True)
    D = arg("focus_distance_mm", focus_distance_mm, positive=True, allow_inf=True)
    require(D > f, "focus_distance_mm", D, "> focal_length_mm",
            "a camera can only focus on objects beyond the focal length")
    return f, N, C, D


@float64
def hyperfocal_distance(focal_length_mm, f_number, acceptable_coc_diameter_mm):
    """Hyperfocal distance: the nearest focus distance whose far DOF limit is infinite.

    .. math:: H = \\frac{f^2}{N C} + f

    Exact for the thin lens: the far-limit denominator ``f^2 - N C (D_s - f)`` of the course
    vanishes at ``D_s = H``. The common approximation is ``f^2/(N C)``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    f_number : array_like
        f-number N, > 0.
    acceptable_coc_diameter_mm : array_like
        Acceptable circle-of-confusion diameter C, mm, > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Hyperfocal distance H from the lens plane, mm. Focused at H, the near limit is H/2.

    Examples
    --------
    >>> round(float(hyperfocal_distance(50.0, 8.0, 0.03)), 3)
    10466.667
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    N = arg("f_number", f_number, positive=True)
    C = arg("acceptable_coc_diameter_mm", acceptable_coc_diameter_mm, positive=True)
    return f * f / (N * C) + f


@float64
def near_limit(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm):
    """Near limit of the depth of field (exact, the course's form).

    .. math:: D_N = \\frac{D_s f^2}{f^2 + N C (D_s - f)}
              = \\frac{f^2}{f^2/D_s + N C (1 - f/D_s)}

    the object distance, nearer than ``D_s``, where :func:`coc_diameter` equals ``C``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    f_number : array_like
        f-number N, > 0.
    acceptable_coc_diameter_mm : array_like
        Acceptable circle-of-confusion diameter C, mm, > 0.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane, mm, > f; ``inf`` gives ``f^2/(N C)``.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Near limit D_N from the lens plane, mm; always finite and in ``(f, D_s)``.

    Examples
    --------
    >>> round(float(near_limit(50.0, 8.0, 0.03, 3000.0)), 3)
    2337.905
    """
    f, N, C, D = _dof_args(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm)
    u = 1.0 / D
    return f * f / (f * f * u + N * C * (1.0 - f * u))


@float64
def far_limit(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm):
    """Far limit of the depth of field (exact, the course's form).

    .. math:: D_F = \\frac{D_s f^2}{f^2 - N C (D_s - f)}
              \\quad\\text{if } D_s < H, \\qquad D_F = \\infty \\text{ if } D_s \\ge H

    the object distance beyond ``D_s`` where :func:`coc_diameter` equals ``C``; infinite when
    the focus distance is at or beyond the :func:`hyperfocal_distance` ``H``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    f_number : array_like
        f-number N, > 0.
    acceptable_coc_diameter_mm : array_like
        Acceptable circle-of-confusion diameter C, mm, > 0.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane, mm, > f; ``inf`` allowed.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Far limit D_F from the lens plane, mm; ``inf`` exactly when ``D_s >= H``.

    Examples
    --------
    >>> round(float(far_limit(50.0, 8.0, 0.03, 3000.0)), 3)
    4185.268
    >>> float(far_limit(50.0, 8.0, 0.03, 20000.0))
    inf
    """
    f, N, C, D = _dof_args(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm)
    H = f * f / (N * C) + f
    u = 1.0 / D
    beyond = D >= H
    denom = xp().where(beyond, 1.0, f * f * u - N * C * (1.0 - f * u))
    return xp().where(beyond, xp().inf, f * f / denom)


@float64
def depth_of_field(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm):
    """Total depth of field, exact: ``D_F - D_N``.

    .. math:: \\mathrm{DOF} = \\frac{2 N C D_s f^2 (D_s - f)}{f^4 - N^2 C^2 (D_s - f)^2}

    (the course's ``2 N C D_s^2 f^2 / (f^4 - N^2 C^2 D_s^2)`` with ``D_s - f`` in place of the
    approximation ``D_s``).

    Parameters
    ----------
    focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm : array_like
        As for :func:`far_limit`.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Depth of field, mm; ``inf`` exactly when ``D_s >= H`` (hyperfocal).

    Examples
    --------
    >>> round(float(depth_of_field(50.0, 8.0, 0.03, 3000.0)), 3)
    1847.363
    """
    return far_limit(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm) - near_limit(
        focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm)


@float64
def depth_of_field_approx(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm):
    """Depth of field, the course's approximation ``2 N C D_s^2 / f^2``.

    Valid when ``N C D_s / f^2 << 1`` (far from hyperfocal) *and* ``D_s >> f`` (not macro):

    .. math:: \\frac{\\mathrm{DOF}_{exact}}{\\mathrm{DOF}_{approx}} =
              \\frac{1 - f/D_s}{1 - \\left(N C (D_s - f)/f^2\\right)^2}

    Parameters
    ----------
    focal_length_mm, f_number, acceptable_coc_diameter_mm : array_like
        As for :func:`far_limit`.
    focus_distance_mm : array_like
        Focus distance D_s from the lens plane, mm, > f and finite.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Approximate depth of field, mm (finite even beyond the hyperfocal distance, where
        it is meaningless).

    Examples
    --------
    >>> round(float(depth_of_field_approx(50.0, 8.0, 0.03, 3000.0)), 3)
    1728.0
    """
    f, N, C, D = _dof_args(focal_length_mm, f_number, acceptable_coc_diameter_mm, focus_distance_mm)
    require(xp().isfinite(D), "focus_distance_mm", D, "finite",
            "the approximation diverges at infinity; use depth_of_field")
    return 2.0 * N * C * D * D / (f * f)


@float64
def default_coc_diameter(sensor_width_mm, sensor_height_mm):
    """Conventional acceptable CoC diameter: the sensor diagonal divided by 1500.

    Parameters
    ----------
    sensor_width_mm, sensor_height_mm : array_like
        Sensor size, mm, > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        CoC diameter, mm (0.0288 mm for 36 x 24 mm, often rounded to 0.03 mm).

    References
    ----------
    Zeiss, "Depth of field and bokeh" (H. H. Nasse, 2010): the d/1500 rule.

    Examples
    --------
    >>> round(float(default_coc_diameter(36.0, 24.0)), 4)
    0.0288
    """
    w = arg("sensor_width_mm", sensor_width_mm, positive=True)
    h = arg("sensor_height_mm", sensor_height_mm, positive=True)
    return xp().hypot(w, h) / 1500.0


# --------------------------------------------------------------------------- sensor and field of view


@float64
def field_of_view_deg(sensor_extent_mm, focal_length_mm, focus_distance_mm=math.inf):
    """Angle of view across a sensor extent (width, height or diagonal).

    .. math:: \\mathrm{FOV} = 2 \\arctan\\frac{w}{2 s}, \\qquad s = \\frac{f D_s}{D_s - f}

    With the default focus at infinity ``s = f``; focusing closer moves the sensor away and
    narrows the view (focus breathing of a thin lens).

    Parameters
    ----------
    sensor_extent_mm : array_like
        Sensor width, height or diagonal, mm, > 0.
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    focus_distance_mm : array_like, optional
        Focus distance D_s from the lens plane, mm, > f. Default ``inf``.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Full angle of view, degrees, in (0, 180).

    Examples
    --------
    >>> round(float(field_of_view_deg(36.0, 50.0)), 2)
    39.6
    """
    w = arg("sensor_extent_mm", sensor_extent_mm, positive=True)
    s = sensor_distance(focal_length_mm, focus_distance_mm)
    return xp().degrees(2.0 * xp().arctan(w / (2.0 * s)))


@float64
def crop_factor(sensor_width_mm, sensor_height_mm):
    """Crop factor: the 36 x 24 mm diagonal over the sensor's diagonal.

    Parameters
    ----------
    sensor_width_mm, sensor_height_mm : array_like
        Sensor size, mm, > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Crop factor (1 for 36 x 24 mm, about 1.53 for APS-C 23.6 x 15.6 mm).

    Examples
    --------
    >>> round(float(crop_factor(17.3, 13.0)), 2)
    2.0
    """
    w = arg("sensor_width_mm", sensor_width_mm, positive=True)
    h = arg("sensor_height_mm", sensor_height_mm, positive=True)
    return FULL_FRAME_DIAGONAL_MM / xp().hypot(w, h)


@float64
def equivalent_focal_length_35mm(focal_length_mm, crop_factor):
    """35 mm-equivalent focal length: the focal length giving the same diagonal angle of view
    on a 36 x 24 mm sensor, ``f * crop``.

    Parameters
    ----------
    focal_length_mm : array_like
        Focal length f, mm, > 0.
    crop_factor : array_like
        Crop factor of the sensor (see :func:`crop_factor`), > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        Equivalent focal length, mm.

    Examples
    --------
    >>> float(equivalent_focal_length_35mm(50.0, 1.5))
    75.0
    """
    f = arg("focal_length_mm", focal_length_mm, positive=True)
    k = arg("crop_factor", crop_factor, positive=True)
    return f * k


# The exposure triangle lives in lensfit.exposure; its functions are part of this API too.
from lensfit.exposure import equivalent_f_number, equivalent_iso, equivalent_shutter_s, exposure_value  # noqa: E402
