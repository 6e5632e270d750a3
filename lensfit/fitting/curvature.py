"""Field curvature: where a setting's samples can show it, whether they do, and its estimate.

The in-focus inverse distance at field angle ``a`` is ``1/X + kappa tan^2(a)`` (``lensfit.fitting``
notes; ``kappa`` in dioptres per unit ``tan^2``), fitted per setting where its samples spread
over the field and kept where it differs from 0 by ``FIELD_CURVATURE_Z`` sigma.
"""

from __future__ import annotations

import math

import numpy as np

from lensfit.fitting.constants import FIELD_CURVATURE_MIN_SAMPLES, FIELD_CURVATURE_MIN_SPREAD, FIELD_CURVATURE_Z
from lensfit.fitting.data import FitData
from lensfit.fitting.model import Layout
from lensfit.fitting.result import Estimate


def field_spread(data: FitData, k: int) -> bool:
    """Whether setting ``k``'s samples can show field curvature: every one's field known, enough
    of them, spread over the field."""
    f2 = data.field2[data.setting == k]
    return (f2.size >= FIELD_CURVATURE_MIN_SAMPLES and bool(np.all(np.isfinite(f2)))
            and float(np.ptp(f2)) >= FIELD_CURVATURE_MIN_SPREAD)


def significant_curvature(theta, free_idx, cov, m: int, curved: list[int]) -> list[int]:
    """Of the settings ``curved`` (field curvature free in ``theta``, the solution; ``cov`` the
    free parameters' model covariance, inflated by the reduced chi-square where that exceeds 1: a
    test that errs towards leaving the curvature out), those whose curvature differs from 0 by
    ``FIELD_CURVATURE_Z`` sigma."""
    at, pos = Layout(m), {int(j): i for i, j in enumerate(free_idx)}
    return [k for k in curved if abs(theta[at.curvature(k)]) >= FIELD_CURVATURE_Z * math.sqrt(
        max(cov[pos[at.curvature(k)], pos[at.curvature(k)]], 1e-300))]


def curvature_estimate(theta, cov, i: int, fitted: bool, mode: str, possible: bool, z) -> Estimate:
    """The field curvature (dioptres per unit tan^2 of the field angle) as fitted, or why not."""
    if fitted:
        v, sd = float(theta[i]), math.sqrt(max(float(cov[i, i]), 0.0))
        return Estimate(v, sd, (v - z[0] * sd, v + z[0] * sd), (v - z[1] * sd, v + z[1] * sd))
    why = ("not fitted (field_curvature off): 0 assumed" if mode == "off" else
           "not determined: the samples do not give their field radius (field_radius_px), are too few or lie at one "
           "field angle; 0 assumed" if not possible else
           f"not significant (below {FIELD_CURVATURE_Z:g} sigma): 0 assumed, as for a thin lens")
    return Estimate(None, reason=why)
