"""The fit's tunable numbers and input ranges, in one place (each says why it has its value)."""

from __future__ import annotations

import math

import numpy as np



#: Weak prior on each setting's blur floor (px, 1 sigma about 0).
FLOOR_PRIOR_SIGMA_PX = 1.0
#: Where a fitted floor b starts (at least, px), and where it is tried again when the fit ends with
#: it within ``FLOOR_SADDLE_PX`` of 0 (``lensfit.fit.core``). The model takes b^2, so b = 0 is a
#: stationary point whatever the data, and with the robust loss's reweighting it can be a minimum
#: beside one with a floor. Seen on a noisy (ISO 1600) diffraction focus bracket of the standard
#: suite: readings the same to 1e-6 gave a floor of 0 (reduced chi-square 0.8989) in one run and
#: 0.105 px (0.8958) in the other, and N 0.064 % (0.3 sigma) apart; tried again from here, both
#: runs end at the second. (Every solve started from here instead: the same, but the demo's fit
#: 2.6x slower, each solve creeping back to a floor of 0.)
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
#: (``lensfit.fit.uncertainty._image_spread``), and the most it takes (one small
#: eigendecomposition each).
MIN_CLUSTERS = 6
MAX_CLUSTERS = 400
#: The blur estimator's scale error shared by every sample of a fit (relative, 1 sigma): a
#: bias of the estimator's model that does not average out over edges (the per-sample model
#: floor of lensfit.estimators.base does). It multiplies every blur alike, so it moves the
#: aperture and f-number (and the slope and floor) and nothing else. A sample's share is
#: ``BLUR_SCALE_SIGMA`` and ``BLUR_SCALE_BIAS_PX2 / c^2`` in quadrature (c its blur diameter, at least
#: ``BLUR_SCALE_MIN_PX``), weighted over the fit by the information it carries about a scale,
#: ``(c / sigma)^2``. Measured for the edge estimator on exact edges (a half-plane blurred by a
#: uniform disk, integrated over each pixel by Gauss-Legendre nodes; slants 3-33 degrees, two
#: sub-pixel offsets; ``lensfit bench-measure``) since its profile's bins are modelled
#: (``lensfit.estimators.profile.footprint``, 2026-11-28): noise-free -0.46 to +0.42 % at 0.7 px,
#: -0.13 to +0.17 % at 1 px, -0.06 to +0.05 % at 1.5 px, within 0.02 % from 2 px (means over the
#: slants within 0.03 %); under noise 0.005 (40 draws) no bias beyond its standard error (0.3 %
#: at 0.7 px, 0.1 % at 1.5 px). The 1/c^2 term bounds these. Before, the bins' spread (a 1/8 px box
#: the model left out) read every blur wide by about 0.9 % / c^2 (+0.9 % at 1 px, +0.19 % at 2 px),
#: which an even 12 x 12 sub-pixel grid in the exact edges (a pixel 1/1728 px^2 too narrow: -0.46 %
#: at 1 px) had halved; the term was 0.006 px^2. On independent renders (Mitsuba 3, 32 spp) the
#: f-number scattered 0.1 % beyond the readings' own scatter and the calibration's (bias +0.04 to
#: +0.08 %, before the bins were modelled): the constant term. (Until 2026-11-24 one constant
#: 0.25 %, from synth renders at 256 spp: the f-number's 95 % intervals were 4.5x its error on
#: independent renders, 9-14x on synth's.) Readings through the shaped (two-disk) spot model are
#: within 1 % of the true second moment on real-ray spots (tests/test_compound_render.py).
BLUR_SCALE_SIGMA = 0.001
BLUR_SCALE_BIAS_PX2 = 0.0025
BLUR_SCALE_MIN_PX = 0.5
#: The constant where no approximate model stands between the image and the reading: the
#: samples were read without the Airy model (which assumes 550 nm for the light's effective
#: wavelength) from a setting whose calibration found no lens distortion (k1 = k2 = 0, fitted,
#: not given), or found it and the reading was taken through it (flag ``distortion_scaled``:
#: ``lensfit.measure`` divides the distortion's stretch across the edge out of the reading; since
#: 2026-11-27, when that took the coverage suite's barrel-distortion set from N +0.11 % to
#: -0.006 %, RMS 0.141 -> 0.076 %, 120 intervals). Such readings are biased by what exact edges
#: and independent renders show: on exact edges no more than the 1/c^2 term bounds; on Mitsuba 3
#: renders at 32 spp (10 seeds, 90 intervals) N +0.08 % with its RMS error over the sigma without
#: any scale term 0.96-1.05 (demo, bracket), with the 0.1 % term 0.73-0.78 (95 % half-width 3.5x
#: the error). Part of that bias is the render's Monte-Carlo noise read through the two-disk
#: refit's per-band weights (``lensfit.estimators.profile._band_variance``: exact edges under
#: 32-spp binomial noise read 0.23 % narrow; a weighting without it took the Mitsuba bracket's N
#: bias +0.09 -> +0.02 %, the demo's stayed +0.08 %; left, README). Where the Airy model is in
#: play, or a distortion the reading was not taken through, and wherever it is not known
#: (samples without their calibration), BLUR_SCALE_SIGMA:
#: the Airy model takes the light's effective wavelength as 550 nm where real channels see a
#: spectrum (synth's camera-raw set, diffracting at 610 / 550 / 465 nm per channel, reads N +0.04
#: to +0.12 % high). The N +0.12 to +0.26 % (RMS error
#: over sigma 1.1-2.0 without the term) that synth's diffraction, camera-raw and distortion sets
#: showed until 2026-11-27 was mostly synth's diffraction filtering the pixel-integrated image;
#: rendered at twice the resolution since, its diffraction sets read N +0.04 to +0.13 %. Under
#: heavy noise the Airy model reads low beside a neighbouring edge (2026-11-27): the ramp that
#: follows the neighbour's Airy tail has a prior (``lensfit.estimators.edge_model.RAMP_PRIOR``),
#: which holds it nearer 0 the noisier the profile. On exact edges (a = 1.03 px, photon noise
#: of a 2000 e- full well and 3 e- read noise, 150-200 copies each): alone +0.02 +- 0.09 % at
#: c = 8 px; with a neighbour 14 px away +0.13 % noise-free, -0.21 +- 0.09 % noisy; 12 px away at
#: c = 3 px -0.45 +- 0.18 %. On a demo stack at f/11 with that noise, -0.08 to -0.28 % against
#: its noise-free readings; the standard suite's ISO 1600 diffraction cases read N +0.09 to
#: +0.24 % (set means). BLUR_SCALE_SIGMA, the constant of such readings, covers that (their 95 %
#: intervals hold N in every case); it is not modelled. A prior five times wider reads -0.07 %
#: at 8 px but scatters 25 % more. On exact 2-D checkerboards (README, "Benchmarks") the
#: neighbours are not most of the noisy bias: modelled exactly, they moved noisy readings by
#: +0.01 to +0.07 % of readings +0.48, -0.04 and -0.33 % off.
BLUR_SCALE_SIGMA_PLAIN = 0.0005


def disk_scale_sigma(c_px: float, plain: bool = False) -> float:
    """The estimator's shared relative scale error for a uniform-disk reading of ``c_px``
    (``plain``: read with no approximate model in play, ``BLUR_SCALE_SIGMA_PLAIN``): the constant
    and the 1/c^2 term in quadrature, two independent sources (until 2026-11-28 added, as if one
    moved with the other)."""
    constant = BLUR_SCALE_SIGMA_PLAIN if plain else BLUR_SCALE_SIGMA
    return math.hypot(constant, BLUR_SCALE_BIAS_PX2 / max(c_px, BLUR_SCALE_MIN_PX) ** 2)
#: A reading through the shaped (two-disk) spot model adds to that a share of its relative
#: difference from the uniform disk's reading of the same edge (``disk_diameter_px``): on real-ray
#: spots the two-disk family is within about a tenth of what the disk misses (1 % where the disk
#: misses by 8-18 %, a retrofocus's cores in a halo at f/5.6; 0.1 % where it misses by 0.7 %), and
#: on a uniform disk the readings agree to the noise. Samples that do not give the disk's reading
#: (written before 2026-11-25) take ``BLUR_SCALE_SIGMA_SHAPED``.
SHAPE_SCALE_SHARE = 0.1
BLUR_SCALE_SIGMA_SHAPED = 0.01
#: Condition number (column-equilibrated Jacobian) above which the fit is degenerate.
MAX_CONDITION = 1e8
LOSSES = ("linear", "huber", "cauchy")
#: An edge whose ends lie at different depths has a blur that varies along it; a one-disk
#: edge fit then reports a power mean of the local blur diameters between the mean (1) and the
#: RMS (2). Measured with the edge estimator on ray-traced squares tilted 40-65 degrees (blur
#: 0-8 px along one edge, crossing focus or not; 24 edges, tests/test_fit_pipeline.py): 1.3 fits
#: within 9.6 % (mean |error| 3.5 %), the mean within 13.5 % (3.8 %), the RMS within 19.5 %
#: (10.3 %); 1.1-1.2 would fit best (3.1 %), within the scatter of one scene's edges (before the
#: profile's bins were modelled: 3.5 % for 1.3, 2.7 % for 1.1-1.2). Fronto-parallel edges are
#: unaffected.
BLUR_POWER_MEAN = 1.3
EDGE_NODES = 16
_GL_X, _GL_W = np.polynomial.legendre.leggauss(EDGE_NODES)
_NODES_T = (_GL_X + 1.0) / 2.0  # positions along the edge, 0..1
_NODES_W = _GL_W / 2.0  # weights summing to 1
_HUBER_K = 1.345
_CAUCHY_C = 2.385
_EPS_PX = 1e-4  # keeps sqrt differentiable exactly at the focus plane with a zero floor
_Z95 = 1.959963984540054

#: The ranges of physically meaningful inputs; anything outside is refused naming the field.
PIXEL_PITCH_RANGE_MM = (1e-4, 1.0)
DISTANCE_RANGE_MM = (0.1, 1e9)
MAX_BLUR_PX = 1e6
MIN_SIGMA_PX = 1e-6
MAX_FOCAL_LENGTH_PX = 1e7

QUANTITIES = ("focal_length_mm", "f_number", "focus_distance_mm", "focus_distance_from_sensor_mm",
              "sensor_distance_mm", "aperture_diameter_mm", "blur_slope_mm2", "blur_floor_px",
              "inverse_focus_distance_per_m")
#: Field curvature (``lensfit.fit.fit``'s ``field_curvature``): the modes; the significance
#: (|kappa| / sigma) at which "auto" keeps it; the fewest samples and the least spread of the
#: squared field tangent (tan^2 of the field angle) over a setting's samples for it to be fitted.
#: Measured on stacks ray traced through the shipped designs (README, "Real (thick) lenses"):
#: kappa at 11-22 sigma on the retrofocus and the telephoto at f/11, 0.4 sigma on synth's
#: thin-lens demo stack.
FIELD_CURVATURE_MODES = ("auto", "on", "off")
FIELD_CURVATURE_Z = 3.0
FIELD_CURVATURE_MIN_SAMPLES = 12
FIELD_CURVATURE_MIN_SPREAD = 1e-3
