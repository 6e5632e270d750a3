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
(tests/synth/test_spectral.py measures this).
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

Layout: ``prescription`` (surfaces, paraxial data, real rays), ``files`` (shipped designs,
inline tables, glasses), ``focus`` (conjugates, best focus, pupils, fastest f-number, internal
focusing by a moving group).
"""

from __future__ import annotations

from synth.lens.prescription import (D_LINE_NM, F_LINE_NM, C_LINE_NM, Glass, abbe_index, Surface, Prescription,
                                     Paraxial, paraxial, reverse, trace)
from synth.lens.files import (lens_dir, list_prescriptions, prescription_from_dict, glass_catalogue,
                              load_prescription)
from synth.lens.focus import (image_z, object_z, axial_rays, disk_grid, BEST_FOCUS_GRID, best_focus_image_z,
                              polychromatic_best_focus_image_z, axial_beam_clipped, fastest_f_number,
                              real_entrance_pupil_diameter, check_focus_group, shift_group, group_travel,
                              internal_focus)

__all__ = [
    'D_LINE_NM', 'F_LINE_NM', 'C_LINE_NM', 'Glass', 'abbe_index', 'Surface', 'Prescription', 'Paraxial',
    'paraxial', 'reverse', 'trace', 'lens_dir', 'list_prescriptions', 'prescription_from_dict',
    'glass_catalogue', 'load_prescription', 'image_z', 'object_z', 'axial_rays', 'disk_grid',
    'BEST_FOCUS_GRID', 'best_focus_image_z', 'polychromatic_best_focus_image_z', 'axial_beam_clipped',
    'fastest_f_number', 'real_entrance_pupil_diameter', 'check_focus_group', 'shift_group', 'group_travel',
    'internal_focus',
]
