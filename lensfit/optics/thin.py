"""The thin-lens equation, the aperture and the circle of confusion (``lensfit.optics``)."""


from __future__ import annotations

from lensfit.optics.checks import arg, float64, namespace, require


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
    return A * namespace(s, z).abs(1.0 - s / z)


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
    return A * s * namespace(D, d).abs(1.0 / D - 1.0 / d)


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
    return (f / N) * _conjugate(f, D) * namespace(D, d).abs(1.0 / D - 1.0 / d)
