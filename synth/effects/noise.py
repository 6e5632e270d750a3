"""``noise``: photon shot noise, dark-current shot noise and read noise, before the readout.

Model
-----
With the mean signal ``mu_e`` (electrons, ``synth.effects.exposure``, dark current included)
each pixel collects ``e ~ Poisson(mu_e)`` electrons (photon and dark shot noise) and the
readout adds Gaussian read noise ``N(0, sigma_r^2)`` (electrons, input-referred), then gain,
black level, rounding to whole DN (quantisation noise 1/12 DN^2) and clipping at the full
well and the white level (``synth.effects.exposure.readout``). So, below clipping,

    mean DN = B + g mu_e,     var DN = g^2 (mu_e + sigma_r^2) + 1/12.

Random numbers: a numpy Generator (PCG64) seeded from (render seed, shot index); it is
created only when this stage runs, so a scene without ``noise`` draws none and two seeds
give the same image.

``[noise]`` (optional): ``shot = false`` or ``read = false`` turn one source off.

Reference: EMVA Standard 1288, release 4.0 (2021), sec. 2 (the linear camera model);
Janesick, *Photon Transfer* (SPIE, 2007).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NAME = "noise"
STREAM = 0x6E6F6973  # "nois": keeps the noise stream apart from any other use of the seed


@dataclass(frozen=True)
class Noise:
    shot: bool = True
    read: bool = True

    def truth(self) -> dict:
        return {"model": "Poisson(mean electrons) + Gaussian read noise, then gain, rounding, clipping",
                "shot": self.shot, "read": self.read, "stream": STREAM}


def generator(seed: int, shot_index: int) -> np.random.Generator:
    """This effect's stream of shot ``shot_index`` (``synth.seeds``)."""
    from synth.seeds import generator as stream_generator

    return stream_generator(seed, shot_index, STREAM)


def draw(mean_e: np.ndarray, params: Noise, read_noise_e: float, rng: np.random.Generator):
    """(electrons, read noise in electrons or None) for one frame."""
    e = rng.poisson(np.maximum(mean_e, 0.0)).astype(np.float64) if params.shot else mean_e
    r = rng.normal(0.0, read_noise_e, size=mean_e.shape) if params.read and read_noise_e > 0 else None
    return e, r


def seconds(width_px: int, height_px: int) -> float:
    return 6e-8 * width_px * height_px
