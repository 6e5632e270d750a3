"""One seed scheme for every random draw of a render.

Everything random in a stack derives from the scene's ``render.seed`` and the shot's index:

- the ray tracer's samples: ``raytrace_seed(seed, k)``, a 32-bit integer for its JAX key (also
  written per image in truth.json as ``seed``);
- every other stream (sensor noise, ...): ``generator(seed, k, stream)``, a NumPy PCG64
  generator from the seed sequence ``[seed, k, stream]``; each effect names its own ``stream``
  constant, so streams never overlap and a stage that does not run draws nothing.

Same seed, same stack, bit for bit on one platform; a different seed changes every stream.
"""

from __future__ import annotations

import numpy as np


def raytrace_seed(seed: int, shot_index: int) -> int:
    """The ray tracer's 32-bit seed for shot ``shot_index``."""
    return (seed * 1_000_003 + shot_index * 7_919) % (1 << 32)


def generator(seed: int, shot_index: int, stream: int) -> np.random.Generator:
    """A NumPy generator for one stream of one shot."""
    return np.random.default_rng(np.random.SeedSequence([seed, shot_index, stream]))
