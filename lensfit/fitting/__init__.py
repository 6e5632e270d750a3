"""Fit the circle-of-confusion model to blur samples: focal length, f-number, focus distance.

Model
-----
For lens setting ``k`` (a focus distance ``D_k`` and f-number ``N_k``; all settings share the
focal length ``f`` and the pupil magnification ``P``) and a sample on an edge whose ends lie at
``d0`` and ``d1`` from the entrance pupil (the lens plane of a thin lens)::

    s_k  = 1 / (1/f - 1/(P D_k))          pinhole distance S = f_px * p, mm (thin lens: P = 1,
                                          the lens-to-sensor distance)
    K_k  = A_k * s_k = f * s_k / N_k       slope of the blur "V" in inverse distance, mm^2
    c(t) = sqrt( (K_k/p)^2 * (1/D_k - 1/d(t))^2 + b_k^2 )              px, local blur
    c    = ( integral_0^1 c(t)^q dt )^(1/q),  q = BLUR_POWER_MEAN = 1.3     px, the edge's blur

with ``d(t)`` linear from ``d0`` to ``d1`` along the edge (16-node Gauss-Legendre), ``p`` the
pixel pitch and ``b_k`` the setting's blur floor in px. For a fronto-parallel edge this is
``sqrt((A s / p)^2 (1/D - 1/d)^2 + b^2)``, the textbook ``(A s / p) |1/D - 1/d|`` with a floor.

Why this form:
- A blur estimator that fits one disk to an edge whose blur varies along it reports something
  between the mean (q = 1) and the RMS (q = 2, the second moment of the mixture) of the local
  diameters; measured on ray-traced tilted squares, q = 1.3 (see ``BLUR_POWER_MEAN``).
- Blur that is not defocus (diffraction: an Airy core of diameter about ``1.68 lambda N`` for a
  disk of equal second moment; residual aberrations; sensor MTF the estimator does not model)
  convolves with the defocus disk, and variances of convolved PSFs add, so the floor adds in
  quadrature. This also makes the model smooth at the focus plane, where ``|.|`` has a kink
  (grad(abs) at 0 is arbitrary, grad(sqrt) at 0 is infinite).
- The floor is fitted per setting with a weak prior ``b_k ~ 0 +- 1 px`` (a regulariser that
  matters only when no sample lies near the focus plane), or fixed by the caller.

Thick lenses (docs/src/explanation/lens-models.md; data_specs/CONVENTIONS.md): with ``A`` the
entrance-pupil diameter, ``P`` the exit/entrance pupil ratio and ``s_x`` the exit pupil's
distance from the sensor, the blur is
``(A s_x / P) |1/D - 1/d|`` and a pinhole calibration centred on the entrance pupil measures
``S = s_x / P``: the V is ``A S |1/D - 1/d|`` whatever ``P`` is, and only the mapping from ``S``
to ``f`` carries ``P``: ``1/f = 1/S + 1/(P D)``. Two or more focus settings that share ``f`` and
``P`` (unit focusing) determine ``P`` (``1/S_k`` is linear in ``1/D_k``); with one setting ``P``
is an assumption (1 by default, with a warning) or a stated prior range.

Observations: the blur samples (weights from each sample's stated 1 sigma) and, per setting,
the calibrated focal length in px, ``f_px = s_k / p`` with its 1 sigma. Parameters (float64,
chosen to stay well conditioned from macro to infinity): ``log f``; per setting the inverse
focus distance ``1000/D_k`` (dioptres, 0 at infinity, allowed to cross it), ``log N_k`` and
``b_k``; ``log P`` (held where assumed; a log-normal prior where a range is given, a very weak
one where it is fitted).

Distances from target poses: a pose solved with a calibrated ``f_px`` that is ``1 + e`` times
the true ``S / p`` puts the board ``1 + e`` times too far (its size in the image is ``f_px``
times its size over its distance), so the calibration's error moves every pose distance of a
setting together. The model therefore reads a sample whose ``distance_source`` is ``"pose"``
at the inverse distance ``(p f_px / S_k) / d``, ``f_px`` the calibrated value and ``S_k`` the
fitted pinhole distance: the calibration's uncertainty reaches the focus distance (one for one)
and the f-number (through f; the aperture ``A`` is the blur slope over the calibrated ``f_px``,
an angle, and does not depend on it). Distances measured otherwise (a manifest's
``distance_mm``, rows without ``distance_source``) are taken as they are.

Error budget: each reported variance is split into its sources (``Estimate.shares``,
results.json ``variance_shares``): the blur readings' scatter, the calibration, what an image's
edges share beyond that (the images' modelled shared distance error and the excess over the
model of the images' cluster-robust spread), the blur estimator's
shared scale error (``BLUR_SCALE_SIGMA`` and ``BLUR_SCALE_BIAS_PX2 / c^2`` in quadrature per sample, the constant
``BLUR_SCALE_SIGMA_PLAIN`` where neither the Airy model nor a lens distortion is in play: a scale on
every blur moves ``A``, ``N``, the slope and the floor alike, and nothing else) and the priors. The model covariance splits exactly as
``H^-1 J_g^T J_g H^-1`` over the row groups ``g`` of the Jacobian. Where every sample of a setting
lies on one side of its focus distance and a floor above 0 was fitted, the difference from the
fit without the floor is a term of its own (``floor_choice``, :mod:`lensfit.fitting.refits`).

Solver: a closed-form start (for each candidate vertex on a grid spanning the data, linear
least squares for the slope and floor in ``c^2``; the best vertex wins), then optimistix
Levenberg-Marquardt for a robust loss (Huber by default, Cauchy for heavy contamination) that
judges each residual against its sigma with its image's shared distance error added (the images'
scatter along the blur's slope beyond what their readings explain: a pose error is not an
outlier): least squares first, then the loss itself with each residual's scale from the solve
before, until estimates and weights settle (the fixed point of iteratively reweighted least
squares, in a few solves). A floor that ends at 0 (the model takes it squared: 0 is a minimum
of its own) is solved once more from ``FLOOR_START_PX`` with the final weights, and the robust
solves go on from there where that fits better. The covariance is
``(J^T W J)^-1`` at the solution,
the blur rows' part scaled by their reduced chi-square (up or down: their own scatter about the
fit, from the samples less the free parameters as degrees of freedom), the calibration's and the
priors' parts as their sigmas state them; the blur part is raised per parameter to the
images' spread where that is larger: the cluster-robust covariance with each image a cluster
(CR2, bias-reduced for the images' leverage; stratified by setting). Propagated to every
derived quantity by the delta method (log space for positive quantities, so intervals stay
positive).

Identifiability: blur at one setting fixes only ``K`` and ``D``; the calibrated
``f_px`` supplies ``s``, hence ``f`` and ``N``. A parameter the data cannot determine (one
distance, blur all below a pixel, no focal length in px, a vertex extrapolated far from the
samples, a relative uncertainty over 20 %) is reported with value ``None`` and the reason and
the capture that would fix it; never a number, NaN or inf.

Layout
------
``data`` (samples in) -> ``start`` (closed-form vertex) -> ``solve`` (compiled
Levenberg-Marquardt, robust reweighting) around ``model`` -> ``uncertainty`` (covariance, delta
method, the images' cluster-robust spread, Cramer-Rao) and ``identifiability`` (what cannot be known, and P)
-> ``result`` (estimates, results file); ``core`` runs them (``fit``); ``constants`` holds the
tunable numbers. ``lensfit.fit(samples)`` is :func:`lensfit.fitting.core.fit`.
"""

from __future__ import annotations

from lensfit.fitting.constants import BLUR_POWER_MEAN, LOSSES, QUANTITIES
from lensfit.fitting.core import fit
from lensfit.fitting.data import FitData, inverse_distance_moments, prepare
from lensfit.fitting.result import Estimate, FitResult, Outcome, compare_with_truth, results_document, write_results
from lensfit.fitting.uncertainty import cramer_rao

__all__ = ["fit", "cramer_rao", "FitResult", "Outcome", "Estimate", "FitData", "prepare", "inverse_distance_moments",
           "results_document", "compare_with_truth", "write_results", "QUANTITIES", "LOSSES", "BLUR_POWER_MEAN"]

