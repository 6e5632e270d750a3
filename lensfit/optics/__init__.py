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

from lensfit.optics.dof import (default_coc_diameter, depth_of_field, depth_of_field_approx, far_limit,
                                hyperfocal_distance, near_limit)
from lensfit.optics.exposure import equivalent_f_number, equivalent_iso, equivalent_shutter_s, exposure_value
from lensfit.optics.formats import crop_factor, equivalent_focal_length_35mm, field_of_view_deg
from lensfit.optics.thin import (FULL_FRAME_DIAGONAL_MM, aperture_diameter, coc_diameter, coc_diameter_image_side,
                                 coc_diameter_object_side, f_number, focus_distance_from_sensor, image_distance,
                                 magnification, object_distance, sensor_distance)

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
