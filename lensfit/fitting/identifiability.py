"""What the data cannot determine, said before and after fitting: the capture's problems, the
pupil magnification P, and field curvature.

Field curvature: the in-focus inverse distance at field angle ``a`` is ``1/X + kappa tan^2(a)``
(``lensfit.fitting`` notes; ``kappa`` in dioptres per unit ``tan^2``), fitted per setting where
its samples spread over the field (:func:`field_spread`) and kept where it differs from 0 by
``FIELD_CURVATURE_Z`` sigma (:func:`significant_curvature`).
"""

from __future__ import annotations

import math

import numpy as np

from lensfit.errors import InputError
from lensfit.fitting.constants import (FIELD_CURVATURE_MIN_SAMPLES, FIELD_CURVATURE_MIN_SPREAD, FIELD_CURVATURE_Z,
                                       MIN_DISTANCE_SPREAD, MIN_USEFUL_BLUR_PX)
from lensfit.fitting.data import FitData
from lensfit.fitting.model import Layout
from lensfit.fitting.result import Estimate
from lensfit.fitting.start import one_side, side_hint, vertex_profile


def capture_problems(data: FitData) -> dict[int, str]:
    """Settings whose capture cannot determine their V, with the reason and the fix."""
    blocked: dict[int, str] = {}
    for k, label in enumerate(data.labels):
        sel = data.setting == k
        d = np.sort(data.distance_mm[sel])
        groups = np.split(d, np.flatnonzero(np.diff(d) / d[:-1] > MIN_DISTANCE_SPREAD) + 1)
        narrow = all((g.max() - g.min()) / g.mean() < MIN_DISTANCE_SPREAD for g in groups)
        if sel.sum() < 4:
            blocked[k] = (f"setting {label!r} has only {int(sel.sum())} measured edge(s); a V needs more: photograph "
                          "the target at 3 or more distances")
        elif (d.max() - d.min()) / np.median(d) < MIN_DISTANCE_SPREAD:
            blocked[k] = (f"every sample of setting {label!r} lies at one distance (~{np.median(d):.0f} mm); blur at "
                          "one distance cannot separate the V's slope from its vertex: photograph the target at 3 or "
                          "more distances, some nearer and some farther than the focus")
        elif len(groups) == 2 and narrow:
            blocked[k] = (f"the samples of setting {label!r} lie at two distances only (~{groups[0].mean():.0f} and "
                          f"~{groups[1].mean():.0f} mm); a V through two distances fits twice (focus between them, or "
                          "beyond both): photograph the target at 3 or more distances")
        elif data.coc_px[sel].max() < MIN_USEFUL_BLUR_PX:
            blocked[k] = (f"every blur of setting {label!r} is below {MIN_USEFUL_BLUR_PX:g} px (largest "
                          f"{data.coc_px[sel].max():.2f} px), where pixel integration, diffraction and aberrations "
                          "dominate: open the aperture or place targets farther from the focus plane")
    return blocked


#: Pupil magnifications outside this range are refused (real photographic lenses: about 0.3
#: for long telephotos to about 4 for extreme retrofocus wide angles).
PUPIL_MAGNIFICATION_RANGE = (0.1, 10.0)
#: Width (1 sigma of log P) of the weak prior that keeps a fitted P in a sane range; a factor of
#: e^3 = 20 either way, so it never matters where the data determine P.
P_PRIOR_SIGMA_LOG = 3.0
#: A fitted P needs focus settings spread enough that its relative 1 sigma stays below this;
#: up to it, P is fitted and its uncertainty widens the intervals of f and N (an assumed P = 1
#: would leave them narrow and wrong by (f/X)(1/P - 1)).
_P_MAX_RELATIVE_SIGMA = 0.3


#: Where the data cannot determine P and none is given, P is carried with this log-normal prior
#: over photographic lenses (median 1, 1 sigma of log P). Real lenses run from telephotos (about
#: 0.5-0.9) through double Gauss and other symmetric designs (0.8-1.2) to retrofocus wide angles
#: (1.2-2.5; docs/src/explanation/lens-models.md); the objectives in optiland's sample catalogue
#: fall among them (Petzval 0.69, telephoto 0.74, Cooke triplet 1.02, double Gauss 1.15, reverse
#: telephoto 1.54). f moves with 1/P (1/f = 1/S + 1/(P X)), which the linear covariance follows
#: in log P: 0.6 makes the 95 % reach, 1 +- 1.18 in 1/P, hold every P from 0.46 up (0.4, the
#: spread of log P itself, missed a P = 0.55 telephoto's f by 0.4 %). The median 1 leaves a thin
#: lens's estimates where an assumed P = 1 put them; the width is the price of not knowing the lens.
PHOTOGRAPHIC_P_SIGMA_LOG = 0.6


def photographic_p_interval(p: float, sigma_log: float, k: float) -> tuple[float, float | None]:
    """P's interval at ``k`` sigmas where the photographic prior carries it: the reach in 1/P that
    the intervals of f and N take (they follow 1/P, linearised in log P: 1/P = (1/p)(1 - k
    sigma_log) to (1/p)(1 + k sigma_log)), so that P's interval states what theirs hold. Its upper
    end is open (None) where that reach passes 1/P = 0: at 95 % every P from about 0.46 up, the
    extreme retrofocus designs (P 4.7-7.2 among data_specs/f_number_survey.toml's) included,
    which a log-normal interval (up to 3.2) had left out though f and N held them."""
    lo = p / (1.0 + k * sigma_log)
    return lo, (None if k * sigma_log >= 1.0 else p / (1.0 - k * sigma_log))


PHOTOGRAPHIC_P_NOTE = ("not determined by the data: the spread of photographic lenses (log-normal, median 1, "
                       f"sigma {PHOTOGRAPHIC_P_SIGMA_LOG:g} in log P) is carried into f and N")


#: How the warning of a fit that carried P over the photographic range begins (said once for a
#: bracket fitted setting by setting: lensfit.fitting.focusing.merge).
P_NOT_DETERMINED = "pupil magnification P not determined"


def photographic_prior(why_not: str) -> tuple[float, tuple[float, float], str]:
    """P's start, its prior (log mean, 1 / log sigma) and the warning where the data cannot
    determine P (``why_not``) and no value or range was given."""
    return 1.0, (0.0, 1.0 / PHOTOGRAPHIC_P_SIGMA_LOG), (
        f"{P_NOT_DETERMINED} ({why_not}): carried over the range of photographic lenses "
        "(telephotos about 0.5 to retrofocus wide angles 2.5), which widens f and N by about (f/X)|1/P - 1|; "
        "give the lens's P (pupil_magnification in stack.toml's [lens], or --pupil-magnification) as a value or "
        "a range, or add a second focus setting, to narrow them")


def pupil_mode(value) -> tuple:
    """("auto",), ("fixed", P) or ("prior", log mean, log sigma) from the ``pupil_magnification`` argument."""
    lo_ok, hi_ok = PUPIL_MAGNIFICATION_RANGE
    req = f"a number between {lo_ok:g} and {hi_ok:g}, a range (lo, hi) within it, or None"

    def number(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo_ok <= v <= hi_ok):
            raise InputError("pupil_magnification", value, req)
        return float(v)

    if value is None:
        return ("auto",)
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise InputError("pupil_magnification", value, req)
        lo, hi = number(value[0]), number(value[1])
        if not lo < hi:
            raise InputError("pupil_magnification", value, req, "give the range as (lo, hi) with lo < hi")
        return ("prior", 0.5 * (math.log(lo) + math.log(hi)), 0.25 * (math.log(hi) - math.log(lo)))
    return ("fixed", number(value))


def p_identifiable(data: FitData, verts: np.ndarray, usable: list[int], fpx_sig: np.ndarray) -> tuple[bool, str]:
    """Whether calibrated settings ``usable`` focus far enough apart to fit P (unit focusing:
    ``1/S_k = 1/f - (1/P)(1/X_k)`` is a line in ``1/X_k``), and if not, why."""
    if len(usable) < 2:
        return False, "one calibrated focus setting cannot determine it"
    x = verts[usable]
    spread = float(np.sqrt(np.sum((x - x.mean()) ** 2)))
    inv_s = 1.0 / (data.focal_length_px[usable] * data.pixel_pitch_mm)
    sd_inv_s = float(np.max(inv_s * fpx_sig[usable] / data.focal_length_px[usable]))
    if spread <= 0 or sd_inv_s / spread > _P_MAX_RELATIVE_SIGMA:
        head = (f"the calibrated settings focus too close together (inverse focus distances within "
                f"{1000 * np.ptp(x):.3g} /m) to determine it")
        if sd_inv_s <= 0:  # intrinsics given as exact: only the spread is missing
            return False, f"{head}; focus the settings at different distances"
        need = np.sqrt(2.0) * sd_inv_s / _P_MAX_RELATIVE_SIGMA  # two settings: spread = difference / sqrt 2
        rel = float(np.max(fpx_sig[usable] / data.focal_length_px[usable]))
        return False, (f"{head}: with calibrations to {100 * rel:.2g} % that needs {1000 * need:.3g} /m, and P to "
                       f"5 % (2 sigma) about {12 * 1000 * need:.3g} /m; focus one setting nearer (stopping it down "
                       "keeps its markers readable)")
    return True, ""


def p_start(data: FitData, verts: np.ndarray, usable: list[int]) -> float:
    """Closed-form P from the line ``1/S_k = 1/f - (1/P) x_k`` through the calibrated settings."""
    x = verts[usable]
    y = 1.0 / (data.focal_length_px[usable] * data.pixel_pitch_mm)
    slope = np.polyfit(x, y, 1)[0] if len(usable) >= 2 and np.ptp(x) > 0 else -1.0
    P = -1.0 / slope if slope < 0 else 1.0
    return float(min(max(P, PUPIL_MAGNIFICATION_RANGE[0]), PUPIL_MAGNIFICATION_RANGE[1]))


def second_vertex(data, theta, full_cov, weights, blocked: dict, fixed_floor: bool, blur_floor_px, scale2: float):
    """Block (in ``blocked``) every setting where a second, distinct V fits about as well as the
    solution (chi-square within 9 scale^2): a discrete ambiguity the covariance misses."""
    at = Layout(len(data.labels))
    for k, label in enumerate(data.labels):
        if k in blocked:
            continue
        sel = data.setting == k
        grid, chi2, _, _ = vertex_profile(data.w_mean[sel], data.coc_px[sel], data.sigma_px[sel], weights[sel],
                                           not fixed_floor, blur_floor_px or 0.0)
        x_fit = theta[at.inv_focus_per_m(k)] / 1000.0
        sd_x = math.sqrt(max(full_cov[at.inv_focus_per_m(k), at.inv_focus_per_m(k)], 0.0)) / 1000.0
        # (the profile is the flat-field one: with field curvature its vertex is the field's mean)
        x_flat = x_fit + theta[at.curvature(k)] / 1000.0 * float(np.mean(np.nan_to_num(data.field2[sel])))
        far = np.abs(grid - x_flat) > max(5 * sd_x, 0.02 * np.ptp(data.w_mean[sel]))
        if far.any() and chi2[far].min() < chi2.min() + 9.0 * scale2:
            alt = grid[far][np.argmin(chi2[far])]
            alt_mm = f"{1 / alt:.0f} mm" if alt > 0 else "infinity"
            blocked[k] = (f"two focus distances fit setting {label!r} about equally well ({1 / x_fit:.0f} mm and "
                          f"{alt_mm}){side_hint(data.w_mean[sel], x_fit)}: add targets on both sides of the focus "
                          "and spread them over more distances")


def one_sided(label: str, focus: Estimate, w_per_m: np.ndarray, x_per_m: float) -> list[str]:
    """A warning where a reported focus distance has every sample on one side of it (and its 95 %
    interval stays finite: focus at infinity has none beyond it): the V's vertex is then
    extrapolated from its slope, which the blur floor and the readings of the smallest blurs bend
    beyond what the interval carries (an end-to-end fuzz's 13 mm f/4 stack, boards all nearer
    than the focus: its focus distance 8.7 % near at 7.6 sigma, its floor 0.81 px against 0)."""
    if focus.value is None or focus.ci95 is None or focus.ci95[1] is None:
        return []
    side = one_side(w_per_m, x_per_m)
    if side is None:
        return []
    where = "beyond" if side == "nearer" else "nearer than"
    return [f"setting {label!r}: every sample is {side} than the focus distance, which is extrapolated from the blur's "
            f"slope (a blur floor and the smallest blurs' readings can bend it beyond its interval): add targets "
            f"{where} the focus distance"]


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
