"""Intrinsics and target poses from detected target points (OpenCV).

For a thin lens, pinhole calibration measures ``focal_length_px = s / p`` (the sensor distance
over the pixel pitch), because the centre of every blur disk lies on the chief ray through
the lens centre. The image scale changes with focus (focus breathing), so each lens setting
gets its own focal length in pixels; the principal point and distortion are shared between
settings (estimated from all views together, each setting's image points scaled about the
principal point by its own focal length, then held fixed per setting). A view whose corners
reproject far worse than the others' is a misdetection and is left out (:func:`outlier_views`).

Planar PnP has a two-fold ambiguity; both IPPE solutions are scored by reprojection error and
the pose is flagged ``ambiguous`` when the runner-up is nearly as good.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np

from lensfit.calibration.sigma import correlated_sigma, focal_information_inverse, jackknife_dof
from lensfit.errors import InputError
from lensfit.calibration.targets import Detection

MIN_VIEWS = 3
MIN_POINTS = 6
#: Below this the focal length's sigma is OpenCV's, or read through the refined corners'
#: covariance where every view states it (:func:`correlated_sigma`).
JACKKNIFE_MIN_VIEWS = 6
DISTORTION_GAIN = 0.9  # keep k1, k2 only if they cut the reprojection RMS below 90 %
#: A view whose corners reproject more than this many times the setting's median view RMS off
#: the setting's calibration, and more than OUTLIER_VIEW_MIN_PX, is a misdetection (markers
#: misread or corners misplaced under heavy blur), not a view the model can fit: one such view
#: of a near setting ray traced through a double Gauss (4.7 px RMS, the others 0.03-0.3 px)
#: moved that setting's focal length by 1.2 % and its reprojection RMS from 0.1 to 1.5 px.
OUTLIER_VIEW_FACTOR = 10.0
OUTLIER_VIEW_MIN_PX = 1.0


@dataclass(frozen=True)
class Intrinsics:
    focal_length_px: float
    principal_point_px: tuple[float, float]
    distortion: tuple[float, ...]  # OpenCV (k1, k2, p1, p2, k3)
    rms_px: float
    views: int
    source: str  # "calibrated" or "manifest"
    #: 1-sigma of ``focal_length_px``: for a calibration the leave-one-view-out jackknife (6+
    #: views) or the estimate from the reprojection residuals (OpenCV's; through the points'
    #: covariance where the corners were refined from edge lines); for manifest intrinsics the
    #: stated ``focal_length_sigma_px``, else 0 (taken as exact)
    focal_length_sigma_px: float = 0.0
    #: how that sigma was found (``SIGMA_METHODS``; "" where not known, e.g. an older file)
    focal_length_sigma_method: str = ""
    #: the degrees of freedom of a jackknife's sigma: ``(sum h)^2 / sum h^2 - 1`` over the views'
    #: leverages ``h`` (the views less one where they inform the focal length alike; about 1.7
    #: where 4 of 10 do, one of them most), at least 1, and ``MODEL_PRIOR_DOF`` more where it is
    #: pooled with the model's; 0 where not a jackknife's, or not known
    focal_length_sigma_dof: float = 0.0
    #: how many views a jackknife's focal length rests on: its own degrees of freedom plus one,
    #: ``(sum h)^2 / sum h^2`` over the views' leverages held within 2 and the views
    #: (:func:`jackknife_dof`); 0 where not a jackknife's, or not known
    informative_views: float = 0.0

    @property
    def camera_matrix(self) -> np.ndarray:
        f = self.focal_length_px
        cx, cy = self.principal_point_px
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class TargetPose:
    """``X_cam = R_cam_target @ X_target + t_cam_target_mm``."""

    R_cam_target: np.ndarray
    t_cam_target_mm: np.ndarray
    rms_px: float
    ambiguous: bool

    def to_camera(self, points_mm: np.ndarray) -> np.ndarray:
        pts = np.asarray(points_mm, np.float64)
        if pts.shape[-1] == 2:
            pts = np.concatenate([pts, np.zeros(pts.shape[:-1] + (1,))], axis=-1)
        return pts @ self.R_cam_target.T + self.t_cam_target_mm


#: How a focal length's sigma was found: the leave-one-view-out jackknife (6+ views); the
#: residuals read through the covariance of corners refined from edge lines (fewer views);
#: OpenCV's residuals taking every point's error as independent; stated in stack.toml; not
#: stated (0, taken as exact).
SIGMA_METHODS = ("jackknife", "corner covariance", "opencv", "manifest", "exact")


def known_intrinsics(entry: dict, shape: tuple[int, int]) -> Intrinsics:
    """Intrinsics given in stack.toml ``[[intrinsics]]`` (principal point defaults to the centre)."""
    h, w = shape
    pp = entry.get("principal_point_px", [(w - 1) / 2, (h - 1) / 2])
    return Intrinsics(float(entry["focal_length_px"]), (float(pp[0]), float(pp[1])),
                      tuple(float(v) for v in entry.get("distortion", [0.0] * 5)), 0.0, 0, "manifest",
                      float(entry.get("focal_length_sigma_px", 0.0)),
                      "manifest" if float(entry.get("focal_length_sigma_px", 0.0)) > 0 else "exact")


def project(points_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (N, 3) -> pixels (N, 2) through the calibrated model (with distortion)."""
    import cv2

    pts = np.asarray(points_cam, np.float64).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intr.camera_matrix, np.asarray(intr.distortion))
    return out.reshape(-1, 2)


@contextlib.contextmanager
def _one_thread():
    """OpenCV's calibration sums in parallel in an order that varies from call to call (focal
    lengths differed by 1e-8 px between identical calls), which made measurements that depend on
    it irreproducible; one thread makes it deterministic and costs little here."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _usable(dets: list[Detection]) -> list[Detection]:
    return [d for d in dets if len(d.ids) >= MIN_POINTS]


def usable_views(dets: list[Detection]) -> int:
    """How many of ``dets`` a calibration can use (``MIN_POINTS`` corners or more); a setting
    needs ``MIN_VIEWS``."""
    return len(_usable(dets))


def calibrate(detections: dict[str, list[Detection]], image_shape: tuple[int, int], *,
              fix_principal_point: bool = True, jackknife: bool = True) -> dict[str, Intrinsics]:
    """Per-setting focal length in pixels, shared principal point and distortion (deterministic:
    see :func:`_one_thread`).

    Parameters
    ----------
    detections : setting label -> detections of targets in that setting's images
    image_shape : (height, width)
    fix_principal_point : hold the principal point at the image centre (recommended unless many
        strongly tilted views constrain it)
    jackknife : the focal length's sigma from leave-one-view-out calibrations (one per view;
        with fewer than ``JACKKNIFE_MIN_VIEWS`` views, from the residuals read through the
        detections' ``point_cov_px2`` where each gives it), else OpenCV's own (for a calibration
        that is only a first step, e.g. before the corners are refined)

    Raises
    ------
    InputError
        A setting with fewer than 3 usable views (argument ``setting``), naming the fix.
    """
    with _one_thread():
        return _calibrate(detections, image_shape, fix_principal_point, jackknife)


def outlier_views(detections: dict[str, list[Detection]], image_shape: tuple[int, int]
                  ) -> dict[str, list[tuple[int, float, float]]]:
    """Per setting, the views that are misdetections: (index into that setting's list, the
    view's RMS reprojection error in px, the median view's), worst first.

    Each setting is calibrated on its own (radial distortion free, principal point at the
    centre); the worst view is left out while its RMS exceeds ``OUTLIER_VIEW_FACTOR`` times the
    median of the views and ``OUTLIER_VIEW_MIN_PX``, and at least ``MIN_VIEWS`` views remain.
    """
    import cv2

    h, w = image_shape
    flags = (cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
             | cv2.CALIB_FIX_PRINCIPAL_POINT)
    K0 = np.array([[1.0, 0.0, (w - 1) / 2], [0.0, 1.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    out: dict[str, list[tuple[int, float, float]]] = {}
    with _one_thread():
        for label, dets in detections.items():
            keep = [j for j, d in enumerate(dets) if len(d.ids) >= MIN_POINTS]
            while len(keep) > MIN_VIEWS:
                per_view = cv2.calibrateCameraExtended(
                    [dets[j].object_points_mm.astype(np.float32) for j in keep],
                    [dets[j].image_points_px.astype(np.float32) for j in keep], (w, h), K0.copy(), np.zeros(5),
                    flags=flags, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10))[7]
                errors = np.ravel(per_view)
                worst, median = int(np.argmax(errors)), float(np.median(errors))
                if errors[worst] <= max(OUTLIER_VIEW_FACTOR * median, OUTLIER_VIEW_MIN_PX):
                    break
                out.setdefault(label, []).append((keep.pop(worst), float(errors[worst]), median))
    return out


def _calibrate(detections: dict[str, list[Detection]], image_shape: tuple[int, int],
               fix_principal_point: bool, with_jackknife: bool) -> dict[str, Intrinsics]:
    for label, dets in detections.items():
        if len(_usable(dets)) < MIN_VIEWS:
            raise InputError("setting", label, f"seen in at least {MIN_VIEWS} images with {MIN_POINTS}+ detected "
                             "corners", f"only {len(_usable(dets))} usable view(s); add views of the targets (some "
                             "tilted by 20-40 degrees) in this setting")
    return _Calibration(detections, image_shape, fix_principal_point, with_jackknife).intrinsics()


class _Calibration:
    """One calibration of every setting (:func:`calibrate`), step by step: OpenCV's runs under the
    flags it settles on (:meth:`run`), the distortion the data ask for (:meth:`choose_distortion`),
    the focal length's sigma (:meth:`focal_sigma`) and each setting's intrinsics
    (:meth:`intrinsics`)."""

    def __init__(self, detections: dict[str, list[Detection]], image_shape: tuple[int, int],
                 fix_principal_point: bool, with_jackknife: bool):
        import cv2

        h, w = image_shape
        self.cv2, self.size, self.detections, self.with_jackknife = cv2, (w, h), detections, with_jackknife
        self.flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
        if fix_principal_point:
            self.flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        self.K0 = np.array([[1.0, 0.0, (w - 1) / 2], [0.0, 1.0, (h - 1) / 2], [0.0, 0.0, 1.0]])

    def run(self, dets, K, dist, extra):
        """OpenCV's calibration of ``dets`` from ``K``, ``dist`` under the flags and ``extra``:
        (RMS, K, distortion, the focal length's sigma, its entry of the inverse information, poses)."""
        cv2 = self.cv2
        obj = [d.object_points_mm.astype(np.float32) for d in _usable(dets)]
        img = [d.image_points_px.astype(np.float32) for d in _usable(dets)]
        rms, K, dist, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(
            obj, img, self.size, K.copy(), dist.copy(), flags=self.flags | extra,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12))
        # With a fixed aspect ratio OpenCV reports the spread on fy (index 1) and 0 on fx.
        sigma = float(max(np.ravel(std)[0], np.ravel(std)[1]))
        # The focal length's entry of the inverse information (OpenCV's sigma^2 over its noise
        # variance, the sum of squares over points less free parameters), for the leverage.
        points = sum(len(o) for o in obj)
        free = 6 * len(obj) + int(np.count_nonzero(np.ravel(std)))
        unit = sigma**2 / max(rms**2 * points / max(points - free, 1), 1e-300)
        return rms, K, dist, sigma, unit, (rvecs, tvecs)

    def one_camera(self, f_px: dict[str, float], centre: np.ndarray) -> list[Detection]:
        """Every setting's views as one camera's: image points scaled about the principal point
        by the first setting's focal length over their own. Pinhole projection and radial
        distortion act on normalised coordinates, ``u = c + f_k d(x)``, so this is exact; all
        views taken at one focal length instead would fit the settings' few per cent of focus
        breathing with the distortion terms (a telephoto bracket's k1, k2 came out 1.0, -33 and
        moved the focal lengths by 0.3-0.7 %)."""
        ref = f_px[next(iter(f_px))]
        return [Detection(d.target_id, d.object_points_mm, centre + (d.image_points_px - centre) * (ref / f_px[label]),
                          d.ids) for label, dets in self.detections.items() for d in dets]

    def choose_distortion(self) -> tuple[dict[str, tuple], str]:
        """All views calibrated with radial distortion and without ("radial", "plain"), and which is
        kept (the flags then fix k1, k2 where it is "plain").

        Radial distortion only when the data ask for it: it must cut the reprojection error by a
        tenth, over all views or over one setting's (a sharp setting shows what a blurred one's
        noisier corners hide: a double Gauss bracket's far views 0.048 -> 0.037 px, all views
        together less than a tenth, and its far focal length 0.45 % off without it); otherwise
        (narrow views, little distortion) k1, k2 merely trade off against the focal length and
        the principal point."""
        cv2, K0 = self.cv2, self.K0
        plain = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
        gains = []
        if len(self.detections) == 1:
            everything = [d for dets in self.detections.values() for d in dets]
        else:
            f_plain = {}
            for label, dets in self.detections.items():
                rms, K, *_ = self.run(dets, K0, np.zeros(5), plain)
                f_plain[label] = K[0, 0]
                gains.append(self.run(dets, K0, np.zeros(5), 0)[0] / rms)
            everything = self.one_camera(f_plain, K0[:2, 2])
        fits = {"radial": self.run(everything, K0, np.zeros(5), 0),
                "plain": self.run(everything, K0, np.zeros(5), plain)}
        gains.append(fits["radial"][0] / fits["plain"][0])
        kept = "radial" if min(gains) <= DISTORTION_GAIN else "plain"
        if kept == "plain":
            self.flags |= plain
        return fits, kept

    def focal_sigma(self, dets, extra, sigma_opencv, unit, f_all, solution):
        """The focal length's 1 sigma (px) and how it was found (``SIGMA_METHODS``): with
        ``JACKKNIFE_MIN_VIEWS`` views or more the leave-one-view-out spread, each view's shift
        weighted by its leverage; with fewer, the residuals read through the refined corners'
        covariance (:func:`correlated_sigma` at ``solution``: the calibration's K, distortion
        and poses), else OpenCV's sigma, either with ``MODEL_PRIOR_DOF`` degrees of freedom (its
        worth as the jackknife's prior: 3-5 views cannot show how far they disagree).

        OpenCV's sigma assumes independent corner errors; corners on blurred views err per view
        (the views disagree by more than noise explains), which the jackknife sees directly. On
        the demo stack: OpenCV 2.4 px, jackknife 1.7 px, actual error 0.7 px. The plain
        jackknife overstates the spread where a few views carry most of what is known of the
        focal length (the tilted ones): dropping a view of share ``h`` of that information moves
        the estimate by its error over ``1 - h``, while that error is ``sqrt(1 - h)`` of the
        noise. Each squared shift is therefore weighted by ``1 - h`` (the CR2 cluster-robust
        variance of Bell and McCaffrey, unbiased for a linear model), ``1 - h`` read from the
        focal length's inverse information with and without the view. Simulated calibrations
        with independent corner noise, 4 of 12 views tilted: the plain jackknife's sigma was
        1.17-1.27x the spread of 80 draws, the weighted one 0.97-1.08x
        (tests/calibration/test_calibration_sigma.py). That variance is pooled with the model's, the residuals
        read through the corners' covariance, as a prior worth ``MODEL_PRIOR_DOF`` degrees of
        freedom.
        """
        usable = _usable(dets)
        n = len(usable)
        if not self.with_jackknife:
            return sigma_opencv, "opencv", 0.0, 0.0
        flags = self.flags
        # the model's sigma: through the refined corners' covariance, else OpenCV's model
        model, method = correlated_sigma(usable, *solution, flags | extra), "corner covariance"
        if model is None:
            model, method = correlated_sigma(usable, *solution, flags | extra, independent=True), "opencv"
        if n < JACKKNIFE_MIN_VIEWS:
            # too few views for a jackknife: the model's sigma alone, worth the degrees of freedom
            # it has as the jackknife's prior (it misses where the views disagree beyond the
            # corners' noise, which few views cannot show)
            return (sigma_opencv if model is None else model), method, MODEL_PRIOR_DOF, 0.0
        # each leave-one-out calibration started from the whole one's intrinsics: the same
        # minimum (sigma within 1e-7), 13 % less time than OpenCV's own start from homographies;
        # the leverages from the inverse information equilibrated (OpenCV's reported sigma
        # truncates it on narrow views: correlated_sigma)
        weighted, guess = 0.0, extra | self.cv2.CALIB_USE_INTRINSIC_GUESS
        unit = focal_information_inverse(usable, *solution, flags | extra) or unit
        leverages = []
        for i in range(n):
            subset = usable[:i] + usable[i + 1:]
            _, K_i, dist_i, _, unit_i, poses_i = self.run(subset, solution[0], solution[1], guess)
            unit_i = focal_information_inverse(subset, K_i, dist_i, poses_i, flags | guess) or unit_i
            kept = min(unit / unit_i, 1.0) if unit_i > 0 else 1.0
            weighted += (K_i[0, 0] - f_all) ** 2 * kept
            leverages.append(1.0 - kept)
        dof = jackknife_dof(leverages)
        views = dof + 1.0
        if model is None:
            return float(np.sqrt(weighted)), "jackknife", dof, views
        # the model's variance as a prior worth MODEL_PRIOR_DOF degrees of freedom
        return (float(np.sqrt((dof * weighted + MODEL_PRIOR_DOF * model**2) / (dof + MODEL_PRIOR_DOF))), "jackknife",
                dof + MODEL_PRIOR_DOF, views)

    def setting(self, dets, K_start, dist_start, extra) -> Intrinsics:
        """One setting's intrinsics, calibrated from ``K_start``, ``dist_start`` under ``extra``."""
        rms, K, dist, sigma, unit, poses = self.run(dets, K_start, dist_start, extra)
        return Intrinsics(float(K[0, 0]), (float(K[0, 2]), float(K[1, 2])), tuple(float(v) for v in dist.ravel()),
                          float(rms), len(_usable(dets)), "calibrated",
                          *self.focal_sigma(dets, extra, sigma, unit, float(K[0, 0]), (K, dist, poses)))

    def intrinsics(self) -> dict[str, Intrinsics]:
        """Every setting's intrinsics. Shared principal point and distortion from all views on one
        scale, each setting's focal length with them held, then once more on the scale those
        focal lengths give."""
        cv2 = self.cv2
        fits, kept = self.choose_distortion()
        if len(self.detections) == 1:
            (label, dets), = self.detections.items()
            return {label: self.setting(dets, self.K0, np.zeros(5), 0)}
        fixed = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
        _, K_all, dist_all, *_ = fits[kept]  # all views on one scale, with the distortion the data ask for
        f_px = {label: self.run(dets, K_all, dist_all, fixed)[1][0, 0] for label, dets in self.detections.items()}
        _, K_all, dist_all, *_ = self.run(self.one_camera(f_px, K_all[:2, 2]), self.K0, np.zeros(5), 0)
        return {label: self.setting(dets, K_all, dist_all, fixed) for label, dets in self.detections.items()}


#: A jackknife's variance is pooled with the model's (the residuals read through the refined
#: corners' covariance, :func:`lensfit.calibration.sigma.correlated_sigma`; else through
#: OpenCV's model of independent points) as a prior worth this many degrees of freedom:
#: ``(nu s_jk^2 + MODEL_PRIOR_DOF s_model^2) / (nu + MODEL_PRIOR_DOF)`` with ``nu +
#: MODEL_PRIOR_DOF`` degrees of freedom (the conjugate update of a scaled inverse chi-square).
#: Why pool: a jackknife on few informative views is as variable as they are few (on its own it
#: can fall to 1/50 of the error, or state intervals 16x the error through t(1)), and the model
#: alone misses where the views disagree by more than the corners' noise says. Why 2: on the
#: calibrations of 6-10 views of random scenes (tests/measurement/test_random_scenes.py draws such scenes)
#: it brings 95 % coverage to 92-97 % at a half-width about 4.7x the error; with 4 or more the
#: coverage falls below 95 %.
MODEL_PRIOR_DOF = 2.0
#: Below these degrees of freedom a calibration's jackknife says so (:func:`few_informative_views`).
FEW_VIEWS_DOF = 3.0


def few_informative_views(intrinsics: dict[str, Intrinsics]) -> list[str]:
    """Warnings for calibrations whose focal length rests on few of their views (the jackknife's
    own degrees of freedom, ``informative_views`` less one, under ``FEW_VIEWS_DOF``,
    :func:`jackknife_dof`; before its pooling with the model), or on too few for a jackknife at
    all: its interval is then wide, and more views, tilted ones, would narrow it."""
    out = []
    for label, v in intrinsics.items():
        if v.focal_length_sigma_method == "jackknife" and 0.0 < v.informative_views - 1.0 < FEW_VIEWS_DOF:
            out.append(f"setting {label!r}: its focal length rests on about {v.informative_views:.1f} of its "
                       f"{v.views} views, its interval on Student's t with {v.focal_length_sigma_dof:.1f} degrees of "
                       "freedom (wide); add views of the targets tilted by 20-40 degrees")
        elif (v.source == "calibrated" and v.focal_length_sigma_method in ("corner covariance", "opencv")
              and 0 < v.focal_length_sigma_dof < math.inf):
            out.append(f"setting {label!r}: its focal length rests on {v.views} views, too few for their spread to "
                       f"be measured ({JACKKNIFE_MIN_VIEWS} or more): its sigma is the corners' model's, its interval "
                       f"on Student's t with {v.focal_length_sigma_dof:.0f} degrees of freedom (wide); add views of the "
                       "targets, tilted by 20-40 degrees")
    return out


def estimate_pose(det: Detection, intr: Intrinsics) -> TargetPose | None:
    """Pose of a planar target; None with fewer than 4 points."""
    import cv2

    if len(det.ids) < 4 or not np.all(np.isfinite(det.image_points_px)):
        return None
    obj = det.object_points_mm.astype(np.float64).reshape(-1, 1, 3)
    img = det.image_points_px.astype(np.float64).reshape(-1, 1, 2)
    K, dist = intr.camera_matrix, np.asarray(intr.distortion)
    with _one_thread():
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if n == 0 or not all(np.all(np.isfinite(v)) for v in (*rvecs, *tvecs)):
            # IPPE in float64 returns NaN for some near fronto-parallel squares (seen with
            # OpenCV 5.0 on a 4-corner target); SQPnP has no such degeneracy (one solution), but
            # refuses, with an assertion, a target too small in the image (its normalised points'
            # variance under 1e-5 or so: a 4-corner square some metres away): no pose then.
            try:
                n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_SQPNP)
            except cv2.error:
                return None
    if n == 0 or not all(np.all(np.isfinite(v)) for v in (*rvecs, *tvecs)):
        return None
    errs = np.asarray(errs).ravel()
    order = np.argsort(errs)
    best = order[0]
    with _one_thread():
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[best].copy(), tvecs[best].copy())
    R, _ = cv2.Rodrigues(rvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj - img) ** 2, axis=-1))))
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(tvec)) and np.isfinite(rms)):
        return None
    ambiguous = bool(n > 1 and errs[order[1]] < 1.5 * errs[best] + 0.05)
    return TargetPose(R, tvec.ravel().astype(np.float64), rms, ambiguous)
