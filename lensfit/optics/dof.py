"""Depth of field: hyperfocal distance, near and far limits (``lensfit.optics``)."""

from __future__ import annotations

from lensfit.optics.checks import arg, float64, namespace, require


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
    xp = namespace(f, N, C, D)
    denom = xp.where(beyond, 1.0, f * f * u - N * C * (1.0 - f * u))
    return xp.where(beyond, xp.inf, f * f / denom)


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
    require(namespace(D).isfinite(D), "focus_distance_mm", D, "finite",
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
    return namespace(w, h).hypot(w, h) / 1500.0
