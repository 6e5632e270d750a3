"""``chromatic_aberration``: longitudinal (focus) and lateral (magnification) colour errors.

Model
-----
Rendering turns to three channels (red, green, blue); green is the reference, rendered with
the scene's lens.

*Longitudinal* (axial) CA: each channel's focal length differs by ``focal_shift_mm[c]``
(dispersion of the glass). The sensor and the aperture stop stay where the green lens put
them, so channel c focuses at ``1/D_c = 1/(f + df_c) - 1/s`` and its blur is
``A s |1/D_c - 1/z|`` (``synth.geometry.ChannelCamera``; ``1/D_c < 0`` means focused beyond
infinity). Each channel is rendered by the scene's method with its own camera.

*Lateral* (transverse) CA: channel c's image is scaled about the principal point by
``magnification[c]`` (e.g. 1.0005 for red), applied in the resampling of
``synth.effects.distortion``.

==========================  ======  ==================================================
parameter                   unit    meaning
==========================  ======  ==================================================
``focal_shift_mm``          mm      [red, green, blue] focal-length change (green 0)
``magnification``                   [red, green, blue] image scale (green 1)
==========================  ======  ==================================================

Reference: Kingslake & Johnson, *Lens Design Fundamentals*, 2nd ed., ch. 5 (chromatic
aberration); Kang, "Automatic removal of chromatic aberration from a single image", CVPR 2007
(the per-channel magnification model of lateral CA).
"""

from __future__ import annotations

from dataclasses import dataclass

NAME = "chromatic_aberration"
CHANNELS = ("red", "green", "blue")


@dataclass(frozen=True)
class ChromaticAberration:
    focal_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    magnification: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def longitudinal(self) -> bool:
        return any(v != 0.0 for v in self.focal_shift_mm)

    @property
    def lateral(self) -> bool:
        return any(v != 1.0 for v in self.magnification)

    def channel_cameras(self, camera) -> list:
        """One camera per channel (the reference camera itself where the shift is 0)."""
        from synth.geometry import ChannelCamera

        return [camera if df == 0.0 else ChannelCamera.for_channel(camera, camera.focal_length_mm + df)
                for df in self.focal_shift_mm]

    def truth(self, camera) -> dict:
        cams = self.channel_cameras(camera)
        return {"channels": list(CHANNELS), "focal_shift_mm": list(self.focal_shift_mm),
                "magnification": list(self.magnification),
                "channel_focal_length_mm": [c.focal_length_mm for c in cams],
                "channel_inverse_focus_distance_per_mm": [c.inverse_focus_distance_per_mm for c in cams],
                "channel_focus_distance_mm": [1.0 / c.inverse_focus_distance_per_mm
                                              if c.inverse_focus_distance_per_mm > 0 else None
                                              for c in cams]}
