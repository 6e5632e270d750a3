"""The fit's tunable numbers and input ranges, in one place (each says why it has its value)."""

from __future__ import annotations

import math

import numpy as np



#: Weak prior on each setting's blur floor (px, 1 sigma about 0).
FLOOR_PRIOR_SIGMA_PX = 1.0
#: Where a fitted floor b starts (at least, px), and where it is tried again when the fit ends with
#: it within ``FLOOR_SADDLE_PX`` of 0 (``lensfit.fitting.core``). The model takes b^2, so b = 0 is a
#: stationary point whatever the data, and with the robust loss's reweighting it can be a minimum
#: beside one with a floor: readings the same to 1e-6 can end at either, N 0.3 sigma apart.
#: Solved again from here, they end at the one that fits better. Not every solve starts here:
#: where the floor is 0, each would creep back to it, at several times the cost.
FLOOR_START_PX = 0.3
FLOOR_SADDLE_PX = 1e-3
#: A parameter whose relative 1 sigma exceeds this is reported as not identifiable.
MAX_RELATIVE_SIGMA = 0.2
#: Samples whose distances spread less than this (relative) count as one distance.
MIN_DISTANCE_SPREAD = 0.02
#: Below this every measured blur is pixel integration, diffraction and aberration.
MIN_USEFUL_BLUR_PX = 1.0
#: Least variance factor of the blur readings (their reduced chi-square about the fit scales
#: their part of the covariance, down as well as up): a numerical guard for exact samples
#: (chi-square 0), under which their sigmas shrink at most 100-fold.
BLUR_SCALE2_MIN = 1e-4
#: Images needed for the images' cluster-robust spread in the covariance
#: (``lensfit.fitting.uncertainty.image_spread``), and the most it takes (one small
#: eigendecomposition each).
MIN_CLUSTERS = 6
MAX_CLUSTERS = 400
#: The blur estimator's scale error shared by every sample of a fit (relative, 1 sigma): a
#: bias of the estimator's model that does not average out over edges (the per-sample model
#: floor of lensfit.estimators.base does). It multiplies every blur alike, so it moves the
#: aperture and f-number (and the slope and floor) and nothing else. A sample's share is
#: ``BLUR_SCALE_SIGMA`` and ``BLUR_SCALE_BIAS_PX2 / c^2`` in quadrature (c its blur diameter, at least
#: ``BLUR_SCALE_MIN_PX``), weighted over the fit by the information it carries about a scale,
#: ``(c / sigma)^2``. The 1/c^2 term bounds the edge estimator's bias on exact edges (a half-plane
#: blurred by a uniform disk and integrated over each pixel, ``lensfit bench-measure``: within
#: +-0.17 % at 1 px, 0.02 % from 2 px, +-0.46 % at 0.7 px). The constant is what independent
#: renders (Mitsuba 3) show beyond the readings' own scatter and the calibration's, about 0.1 %,
#: where an approximate model stands between the image and the reading. Readings through the
#: shaped (two-disk) spot model are within 1 % of the true second moment on real-ray spots
#: (tests/synth/test_compound_render.py). Derivation: docs/src/explanation/error-budget.md.
BLUR_SCALE_SIGMA = 0.001
BLUR_SCALE_BIAS_PX2 = 0.0025
BLUR_SCALE_MIN_PX = 0.5
#: The constant where no approximate model stands between the image and the reading: the
#: samples were read without the Airy model (which takes 550 nm for the light's effective
#: wavelength, where real channels see a spectrum) from a setting whose calibration found no lens
#: distortion (k1 = k2 = 0, fitted, not given), or found it and the reading was taken through it
#: (flag ``distortion_scaled``). Such readings are biased by no more than exact edges show (the
#: 1/c^2 term) and independent renders (Mitsuba 3, 32 spp: N +0.08 %, RMS error over sigma about 1
#: with no scale term at all). Where the Airy model is in play, or a distortion the reading was
#: not taken through, and wherever it is not known (samples without their calibration),
#: ``BLUR_SCALE_SIGMA``: it also covers the Airy model's readings beside a neighbouring edge
#: under heavy noise, whose ramp prior (``lensfit.estimators.edge_model.RAMP_PRIOR``) holds the
#: neighbour's tail nearer 0 the noisier the profile (-0.1 to -0.3 % on exact edges at a 2000 e-
#: full well).
BLUR_SCALE_SIGMA_PLAIN = 0.0005


def disk_scale_sigma(c_px: float, plain: bool = False) -> float:
    """The estimator's shared relative scale error for a uniform-disk reading of ``c_px``
    (``plain``: read with no approximate model in play, ``BLUR_SCALE_SIGMA_PLAIN``): the constant
    and the 1/c^2 term in quadrature: two independent sources, so their variances add."""
    constant = BLUR_SCALE_SIGMA_PLAIN if plain else BLUR_SCALE_SIGMA
    return math.hypot(constant, BLUR_SCALE_BIAS_PX2 / max(c_px, BLUR_SCALE_MIN_PX) ** 2)
#: A reading through the shaped (two-disk) spot model adds to that a share of its relative
#: difference from the uniform disk's reading of the same edge (``disk_diameter_px``): on real-ray
#: spots the two-disk family is within about a tenth of what the disk misses (1 % where the disk
#: misses by 8-18 %, a retrofocus's cores in a halo at f/5.6; 0.1 % where it misses by 0.7 %), and
#: on a uniform disk the readings agree to the noise. Samples that do not give the disk's reading
#: (written by an older lensfit) take ``BLUR_SCALE_SIGMA_SHAPED``.
SHAPE_SCALE_SHARE = 0.1
BLUR_SCALE_SIGMA_SHAPED = 0.01
#: A shaped reading's own model error (1 sigma), as a share of its relative difference from the
#: uniform disk's reading of the same edge: through two disks, and through the radial rings where
#: the data rejected two disks (``lensfit.estimators.radial``). Measured on exact edges of
#: real-ray spots (a 24 mm f/4 retrofocus, an 85 mm f/1.4 Petzval, on the axis and 150-400 px
#: off it): two disks' readings stayed within 0.05-0.25 of that difference of the true second
#: moment (0.3 covers them); the rings' erred by 0-2.8 times it, RMS 1.2 (on the axis 0.3-0.5;
#: the Petzval's near-side spots off the axis, whose comatic tail to one side no symmetric
#: profile holds, 1.3-2.8).
#: Shared by an arm of the V (``lensfit.fitting.uncertainty.arms_part``).
SHAPE_ERROR_SHARE = 0.3
SHAPE_ERROR_SHARE_RADIAL = 1.2
#: Shaped readings a setting needs, nearest in inverse distance on each side, before its spots'
#: departure from uniform disks is taken as known for the readings whose shape was not read
#: (``lensfit.fitting.data._unread_shape_sigma``); the departure from which the fit says so.
UNREAD_SHAPE_MIN = 8
UNREAD_SHAPE_WARN = 0.03
#: Condition number (column-equilibrated Jacobian) above which the fit is degenerate.
MAX_CONDITION = 1e8
LOSSES = ("linear", "huber", "cauchy")
#: An edge whose ends lie at different depths has a blur that varies along it; a one-disk
#: edge fit then reports a power mean of the local blur diameters between the mean (1) and the
#: RMS (2). Measured with the edge estimator on ray-traced squares tilted 40-65 degrees (blur
#: 0-8 px along one edge, crossing focus or not; 24 edges, tests/measurement/test_fit_pipeline.py): 1.3 fits
#: within 9.6 % (mean |error| 3.5 %), the mean within 13.5 % (3.8 %), the RMS within 19.5 %
#: (10.3 %); 1.1-1.2 would fit best (3.1 %), within the scatter of one scene's edges.
#: Fronto-parallel edges are unaffected.
BLUR_POWER_MEAN = 1.3
EDGE_NODES = 16
_GL_X, _GL_W = np.polynomial.legendre.leggauss(EDGE_NODES)
NODES_T = (_GL_X + 1.0) / 2.0  # positions along the edge, 0..1
NODES_W = _GL_W / 2.0  # weights summing to 1
HUBER_K = 1.345
CAUCHY_C = 2.385
EPS_PX = 1e-4  # keeps sqrt differentiable exactly at the focus plane with a zero floor
Z95 = 1.959963984540054

#: The ranges of physically meaningful inputs; anything outside is refused naming the field.
PIXEL_PITCH_RANGE_MM = (1e-4, 1.0)
DISTANCE_RANGE_MM = (0.1, 1e9)
MAX_BLUR_PX = 1e6
MIN_SIGMA_PX = 1e-6
MAX_FOCAL_LENGTH_PX = 1e7

QUANTITIES = ("focal_length_mm", "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm",
              "sensor_distance_mm", "aperture_diameter_mm", "blur_slope_mm2", "blur_floor_px",
              "inverse_focus_distance_per_m")
#: Field curvature (``lensfit.fitting.fit``'s ``field_curvature``): the modes; the significance
#: (|kappa| / sigma) at which "auto" keeps it; the fewest samples and the least spread of the
#: squared field tangent (tan^2 of the field angle) over a setting's samples for it to be fitted.
#: Measured on stacks ray traced through the shipped designs (lensfit bench-lenses; docs/src/guides/real-lenses.md):
#: kappa at 11-22 sigma on the retrofocus and the telephoto at f/11, 0.4 sigma on synth's
#: thin-lens demo stack.
FIELD_CURVATURE_MODES = ("auto", "on", "off")
FIELD_CURVATURE_Z = 3.0
FIELD_CURVATURE_MIN_SAMPLES = 12
FIELD_CURVATURE_MIN_SPREAD = 1e-3
