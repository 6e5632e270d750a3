"""Thin-lens camera geometry shared by the render methods and the ground truth.

Conventions (``data_specs/CONVENTIONS.md``): camera frame at the lens centre, +z towards the
scene, +x right, +y down the stored image; pixel centres at integer coordinates; the stored
image is re-inverted, so the chief ray of pixel (u, v) has direction
((u - cx) p / s, (v - cy) p / s, 1).

The thin-lens ray in five named steps (as in pbrt's ``ThinLensCamera``):

1. sensor point: pixel sample (u, v) -> (x_s, y_s) = ((u - cx) p, (v - cy) p) on the re-inverted sensor;
2. lens sample: a point (l_x, l_y) on the aperture disk of diameter A;
3. point on the plane of focus: the chief ray through the lens centre meets z = D_s at
   (x_s, y_s) * D_s / s;
4. the ray from the lens point through that point: direction
   (x_s / s - l_x / D_s, y_s / s - l_y / D_s, 1), parametrised by its depth z (so ``t = z``);
5. nearest intersection with the scene's planes.

Written with ``1/D_s`` so that focus at infinity (1/D_s = 0) is exact.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lensfit import optics


def rotation_from_tilt(tilt_deg) -> np.ndarray:
    """``R_cam_target`` for a target tilted by ``[a, b]`` degrees: R = R_y(b) @ R_x(a).

    An untilted target has its local x, y axes along the camera's x, y and faces the camera.
    """
    a, b = np.radians(np.asarray(tilt_deg, dtype=np.float64))
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return Ry @ Rx


@dataclass(frozen=True)
class Pose:
    """Pose of a planar target: ``X_cam = R_cam_target @ X_target + t_cam_target`` (mm)."""

    R_cam_target: np.ndarray
    t_cam_target: np.ndarray

    @classmethod
    def from_spec(cls, distance_mm: float, tilt_deg, offset_mm) -> "Pose":
        t = np.array([offset_mm[0], offset_mm[1], distance_mm], dtype=np.float64)
        return cls(rotation_from_tilt(tilt_deg), t)

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the target plane in camera coordinates (target +z axis)."""
        return self.R_cam_target[:, 2]

    def to_camera(self, xy_mm: np.ndarray) -> np.ndarray:
        """Target-plane points (..., 2) in mm -> camera coordinates (..., 3)."""
        xy = np.asarray(xy_mm, dtype=np.float64)
        return xy[..., 0:1] * self.R_cam_target[:, 0] + xy[..., 1:2] * self.R_cam_target[:, 1] + self.t_cam_target

    @property
    def fronto_parallel(self) -> bool:
        return bool(np.allclose(self.normal, [0.0, 0.0, 1.0], atol=1e-12))


@dataclass(frozen=True)
class ThinLensCamera:
    """A thin-lens camera with a centred sensor.

    ==========================  ======  =========================================  ===========
    parameter                   unit    meaning                                    valid range
    ==========================  ======  =========================================  ===========
    ``focal_length_mm``         mm      focal length f                             > 0
    ``f_number``                        f-number N                                 > 0
    ``focus_distance_mm``       mm      focus distance D_s from the lens plane     > f, or inf
    ``pixel_pitch_mm``          mm      pixel pitch p                              > 0
    ``width_px, height_px``     px      image size                                 >= 1
    ==========================  ======  =========================================  ===========
    """

    #: The lens's prescription (``CompoundLensCamera``: a real lens, ray traced surface by surface);
    #: None for the thin lens. The renderers ask this, not which class they were given.
    prescription = None
    #: Spectral samples (nm) a compound lens is rendered at; () = one image at the d line.
    wavelengths_nm = ()

    focal_length_mm: float
    f_number: float
    focus_distance_mm: float
    pixel_pitch_mm: float
    width_px: int
    height_px: int

    @functools.cached_property
    def sensor_distance_mm(self) -> float:
        return float(optics.sensor_distance(self.focal_length_mm, self.focus_distance_mm))

    @functools.cached_property
    def aperture_diameter_mm(self) -> float:
        return float(optics.aperture_diameter(self.focal_length_mm, self.f_number))

    @property
    def inverse_focus_distance_per_mm(self) -> float:
        """1/D_s in 1/mm (0 for focus at infinity)."""
        return 1.0 / self.focus_distance_mm

    @property
    def focal_length_px(self) -> float:
        """Pinhole focal length in pixels, s/p (what geometric calibration measures)."""
        return self.sensor_distance_mm / self.pixel_pitch_mm

    @property
    def principal_point_px(self) -> tuple[float, float]:
        return ((self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0)

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Chief-ray projection of camera points (..., 3) to pixel coordinates (..., 2).

        The centre of the blur disk of an out-of-focus point lies here.
        """
        X = np.asarray(X_cam, dtype=np.float64)
        cx, cy = self.principal_point_px
        k = self.focal_length_px / X[..., 2]
        return np.stack([cx + k * X[..., 0], cy + k * X[..., 1]], axis=-1)

    def coc_diameter_px(self, depth_mm) -> np.ndarray:
        """CoC diameter in pixels of points at depth z (mm): ``A s |1/D_s - 1/z| / p``."""
        c = optics.coc_diameter(self.focal_length_mm, self.f_number, self.focus_distance_mm, depth_mm)
        return np.asarray(c) / self.pixel_pitch_mm


@dataclass(frozen=True)
class ChannelCamera(ThinLensCamera):
    """The camera as one colour channel sees it under longitudinal chromatic aberration.

    The sensor stays where the reference lens put it (``sensor_distance_mm`` of the reference
    camera) and the aperture stop keeps its diameter; the channel's focal length differs, so
    the object distance it focuses on moves: ``1/D_c = 1/f_c - 1/s``. That may be beyond
    infinity (``1/D_c < 0``: every object is blurred), which ``ThinLensCamera`` cannot express;
    here everything is written with the inverse focus distance.
    """

    channel_sensor_distance_mm: float = 0.0
    channel_aperture_diameter_mm: float = 0.0
    channel_inverse_focus_distance_per_mm: float = 0.0

    @classmethod
    def for_channel(cls, reference: ThinLensCamera, focal_length_mm: float) -> "ChannelCamera":
        s = reference.sensor_distance_mm
        A = reference.aperture_diameter_mm
        inv = 1.0 / focal_length_mm - 1.0 / s
        return cls(focal_length_mm=focal_length_mm, f_number=focal_length_mm / A,
                   focus_distance_mm=(1.0 / inv) if inv != 0 else np.inf,
                   pixel_pitch_mm=reference.pixel_pitch_mm, width_px=reference.width_px,
                   height_px=reference.height_px, channel_sensor_distance_mm=s,
                   channel_aperture_diameter_mm=A, channel_inverse_focus_distance_per_mm=inv)

    @property
    def sensor_distance_mm(self) -> float:  # type: ignore[override]
        return self.channel_sensor_distance_mm

    @property
    def aperture_diameter_mm(self) -> float:  # type: ignore[override]
        return self.channel_aperture_diameter_mm

    @property
    def inverse_focus_distance_per_mm(self) -> float:
        return self.channel_inverse_focus_distance_per_mm

    def coc_diameter_px(self, depth_mm) -> np.ndarray:
        z = np.asarray(depth_mm, dtype=np.float64)
        with np.errstate(divide="ignore"):
            inv_z = np.where(np.isinf(z), 0.0, 1.0 / z)
        return (self.channel_aperture_diameter_mm * self.channel_sensor_distance_mm
                * np.abs(self.channel_inverse_focus_distance_per_mm - inv_z) / self.pixel_pitch_mm)


@dataclass(frozen=True)
class CompoundLensCamera(ThinLensCamera):
    """A camera with a real compound lens (``synth.lens.Prescription``), focused by moving the
    whole lens (unit focusing; or by a group inside it, see ``focus_group``: the prescription is
    then the lens as that setting leaves it) so that the focus distance is imaged on the sensor: at the lens's
    best focus for it (``focus_plane = "best"``: the smallest RMS spot of the axial point, where a
    camera's autofocus puts it; spherical aberration moves it from the paraxial image; over all
    of ``wavelengths_nm`` when given) or at its paraxial image (``"paraxial"``, d line).

    ``focal_length_mm`` is the prescription's EFL; ``f_number`` = EFL / entrance-pupil diameter
    (the stop is scaled to it); ``focus_distance_mm`` and every object distance are measured
    from the entrance pupil, the centre a pinhole calibration finds. ``sensor_distance_mm`` is
    the pinhole-equivalent distance ``S = f_px * p`` (chief rays through the entrance pupil land
    at ``S tan(theta)`` paraxially), so projection and the truth's f_px stay those of a pinhole
    at the entrance pupil; ``coc_diameter_px`` is the paraxial thick-lens blur ``A S |1/X - 1/d| / p``.
    The image itself is ray traced through every surface (``synth.raytrace``).
    """

    prescription: Any = None
    focus_plane: str = "best"
    #: Spectral samples (nm) the image is rendered at (``synth.spectral``); () = the d line alone.
    wavelengths_nm: tuple[float, ...] = ()
    #: Internal focusing: the surfaces (first, last) of the group that moved to focus, and how far
    #: (mm, + towards the image) from its design position; ``prescription`` is then the lens with
    #: the group there, and ``focal_length_mm`` its EFL. None: unit focusing.
    focus_group: tuple[int, int] | None = None
    focus_group_shift_mm: float | None = None

    @property
    def scene_origin_z_mm(self) -> float:
        """z (lens coordinates) of the scene frame's origin: the entrance pupil, from which every
        object distance is measured."""
        return self.paraxial.entrance_pupil_z_mm

    def spectral_cameras(self) -> list["SpectralCamera"]:
        """One camera per wavelength of ``wavelengths_nm``: the same lens, stop and sensor with
        the glasses' indices at that wavelength (made once per camera: focus, truth and render
        share them and their paraxial data)."""
        return list(self._spectral_cameras)

    @functools.cached_property
    def _spectral_cameras(self) -> tuple["SpectralCamera", ...]:
        return tuple(SpectralCamera(focal_length_mm=self.focal_length_mm, f_number=self.f_number,
                                    focus_distance_mm=self.focus_distance_mm, pixel_pitch_mm=self.pixel_pitch_mm,
                                    width_px=self.width_px, height_px=self.height_px,
                                    prescription=self.prescription, focus_plane=self.focus_plane,
                                    wavelength_nm=float(w), reference=self)
                     for w in self.wavelengths_nm)

    @functools.cached_property
    def stopped(self):
        """The prescription with its stop set to this f-number."""
        return self.prescription.with_f_number(self.f_number)

    @functools.cached_property
    def paraxial(self):
        from synth.lens import paraxial

        return paraxial(self.stopped)

    @functools.cached_property
    def sensor_z_mm(self) -> float:
        """z of the sensor (lens coordinates: first vertex at 0): the best-focus or paraxial image
        of the axial point at the focus distance."""
        return self.best_focus_z_mm if self.focus_plane == "best" else self.paraxial_image_z_mm

    @functools.cached_property
    def paraxial_image_z_mm(self) -> float:
        """z of the paraxial image of the axial point at the focus distance."""
        from synth.lens import image_z

        return image_z(self.stopped, self.paraxial.entrance_pupil_z_mm - self.focus_distance_mm)

    @functools.cached_property
    def best_focus_z_mm(self) -> float:
        """z where the real rays from the axial point at the focus distance have the smallest RMS
        spot; with ``wavelengths_nm``, the rays of every wavelength together (equal weights: the
        grey image autofocus sees; the d line sets the entrance pupil the distance is from)."""
        from synth.lens import polychromatic_best_focus_image_z

        z_obj = self.paraxial.entrance_pupil_z_mm - self.focus_distance_mm
        rxs = [c.stopped for c in self.spectral_cameras()] if self.wavelengths_nm else [self.stopped]
        return polychromatic_best_focus_image_z(rxs, z_obj)

    @functools.cached_property
    def paraxial_inverse_focus_distance_per_mm(self) -> float:
        """1/distance (1/mm, from the entrance pupil) of the object whose paraxial image is on the
        sensor; negative when that object is virtual (the sensor in front of the rear focal point,
        as the best focus for infinity is)."""
        from synth.lens import object_z

        return 1.0 / (self.paraxial.entrance_pupil_z_mm - object_z(self.stopped, self.sensor_z_mm))

    @functools.cached_property
    def sensor_distance_mm(self) -> float:
        para = self.paraxial
        return (self.sensor_z_mm - para.exit_pupil_z_mm) / para.pupil_magnification

    def coc_diameter_px(self, depth_mm) -> np.ndarray:
        z = np.asarray(depth_mm, dtype=np.float64)
        with np.errstate(divide="ignore"):
            inv_z = np.where(np.isinf(z), 0.0, 1.0 / z)
        return self.aperture_diameter_mm * self.sensor_distance_mm * np.abs(
            self.inverse_focus_distance_per_mm - inv_z) / self.pixel_pitch_mm

    def truth(self) -> dict[str, Any]:
        """Thick-lens entries of truth.json's setting: distances from the entrance pupil; the
        exit pupil to sensor distance as ``sensor_distance_mm``; the paraxial data."""
        para = self.paraxial
        from_sensor = self.focus_distance_mm + (self.sensor_z_mm - para.entrance_pupil_z_mm)
        inv_paraxial = self.paraxial_inverse_focus_distance_per_mm
        from synth.lens import real_entrance_pupil_diameter

        real_epd = real_entrance_pupil_diameter(self.stopped, para.entrance_pupil_z_mm - self.focus_distance_mm)
        return {"sensor_distance_mm": self.sensor_z_mm - para.exit_pupil_z_mm,
                "real_ray_f_number": para.efl_mm / real_epd,
                "real_entrance_pupil_diameter_mm": real_epd,
                "focus_plane": self.focus_plane,
                "paraxial_focus_distance_mm": 1.0 / inv_paraxial if inv_paraxial > 0 else None,
                "paraxial_inverse_focus_distance_per_mm": inv_paraxial,
                "pinhole_distance_mm": self.sensor_distance_mm,
                "focus_distance_from_sensor_mm": from_sensor if math.isfinite(from_sensor) else None,
                "pupil_magnification": para.pupil_magnification,
                "lens": {"prescription": self.prescription.name, "source": self.prescription.source,
                         "focusing": "unit" if self.focus_group is None else "internal",
                         **({} if self.focus_group is None else {"focus_group": list(self.focus_group),
                                                                 "focus_group_shift_mm": self.focus_group_shift_mm}),
                         "distances_from": "entrance pupil", "sensor_z_mm": self.sensor_z_mm,
                         "paraxial_image_z_mm": self.paraxial_image_z_mm,
                         "best_focus_image_z_mm": self.best_focus_z_mm,
                         "paraxial": para.to_json_dict(),
                         **({"spectral": self.spectral_truth()} if self.wavelengths_nm else {})}}

    def spectral_truth(self) -> dict[str, Any]:
        """Per wavelength: EFL, where the axial point at the focus distance comes to its best
        focus (and how far that is from the sensor: longitudinal colour), the object distance
        from the entrance pupil that is paraxially in focus, and the image height of an
        off-axis point (lateral colour), see ``synth.spectral.spectral_truth``."""
        from synth.spectral import spectral_truth

        return spectral_truth(self)


@dataclass(frozen=True)
class SpectralCamera(CompoundLensCamera):
    """A compound-lens camera at one wavelength: the reference camera's stop (its f-number set
    at the d line) and sensor position (the grey image's best focus), the glasses' indices at
    ``wavelength_nm``; object distances stay measured from the reference entrance pupil. Focus, magnification and blur
    follow from the trace: longitudinal and lateral colour are not added, they come out."""

    wavelength_nm: float = 587.5618
    reference: Any = None

    @functools.cached_property
    def stopped(self):
        return self.reference.stopped.at_wavelength(self.wavelength_nm)

    @functools.cached_property
    def sensor_z_mm(self) -> float:  # type: ignore[override]
        return self.reference.sensor_z_mm

    @property
    def scene_origin_z_mm(self) -> float:
        return self.reference.scene_origin_z_mm
