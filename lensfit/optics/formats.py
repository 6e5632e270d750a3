"""Sensor formats and field of view: crop factor, 35 mm equivalent focal length (``lensfit.optics``)."""

from __future__ import annotations

import math

from lensfit.optics.checks import arg, float64, namespace
from lensfit.optics.thin import FULL_FRAME_DIAGONAL_MM, sensor_distance


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
    xp = namespace(w, s)
    return xp.degrees(2.0 * xp.arctan(w / (2.0 * s)))


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
    return FULL_FRAME_DIAGONAL_MM / namespace(w, h).hypot(w, h)


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
