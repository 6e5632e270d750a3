"""The f-number a lens is sold by, from the one its blur shows.

A blur-versus-depth fit measures the cone of the real rays: the spot's second moment grows with
the defocus as the real rays' spread of angles. A lens's f-number is paraxial, EFL over the
entrance pupil's diameter, what its aperture ring says. For an ideal lens (a renderer's thin-lens
camera) the two are the same; for a real one pupil aberrations, the non-paraxial angles of a fast
cone and the real best focus part them: over 19 published designs wide open (optiland's sample
objectives and the designs lensfit ships, ``data_specs/f_number_survey.toml``, written by
``python -m lensfit.bench.designs``) the blur's f-number ran 0.5 % below to 7.1 % above EFL/EPD
(a telephoto at f/5.6: +4.2 %; a Petzval at f/1.4: +7.1 %; most within 2 %), about half that a
stop down.

So unless the lens is declared ideal (stack.toml ``[lens] ideal = true``, which synth writes for
its thin lens, or ``fit(..., ideal_lens=True)``), the f-number and aperture diameter reported are
the nominal ones: the blur's reading divided (the diameter multiplied) by the survey's ratio, a
log-normal of the designs' mean and spread wide open (the photographer's usual case; stopped
down the spread is about halved, so there it is conservative), the spread widened to the
prediction interval of a new design from a sample of 19 (x 1.10) and further, until the 95 %
interval holds every surveyed design (the ratios are skewed: 2.7 % in log). The blur's own
reading stays beside it as ``f_number_effective``.
"""

from __future__ import annotations

import functools
import math
import statistics
from typing import Any

#: The variance source the term carries in the error budget (results.json ``variance_shares``).
SOURCE = "lens_design"


@functools.cache
def design_spread() -> tuple[float, float]:
    """Mean and spread of log(N_effective / (EFL/EPD)) over the survey's designs wide open. The
    spread is the one a new lens's ratio has about a mean drawn from a sample of n designs: the
    sample's standard deviation times ``t(0.975, n - 1) / z(0.975) * sqrt(1 + 1/n)`` (1.10 for the
    19 designs), so that the Gaussian 95 % interval the fit states is the t prediction interval,
    and at least the largest distance of a surveyed design from the mean over z(0.975), so that
    the interval holds every design surveyed (2.7 %: the f/1.4 Petzval's +7.1 %)."""
    import tomllib

    from scipy import stats

    from lensfit.io.specs import specs_dir

    rows = tomllib.loads((specs_dir() / "f_number_survey.toml").read_text())["design"]
    logs = [math.log(r["ratio"]) for r in rows if r["stops_down"] == 0]
    n = len(logs)
    z = float(stats.norm.ppf(0.975))
    predictive = float(stats.t.ppf(0.975, n - 1) / z) * math.sqrt(1.0 + 1.0 / n)
    mean = statistics.fmean(logs)
    # The ratios are skewed (most designs within 2 %, a fast Petzval +7.1 %): a Gaussian fitted to
    # them ends its 95 % interval inside the sample's own range, which holds a new design only 90 %
    # of the time ((n - 1) / (n + 1)). The spread is at least wide enough for the interval to hold
    # every surveyed design.
    return mean, max(statistics.stdev(logs) * predictive, max(abs(x - mean) for x in logs) / z)


def definition(ideal: bool) -> dict[str, Any]:
    """results.json ``f_number_definition``: which f-number is reported, and how."""
    if ideal:
        return {"reported": "effective", "design_log_ratio": None,
                "note": "an ideal lens (declared): the f-number is the blur's own, EFL / entrance pupil"}
    mean, sd = design_spread()
    return {"reported": "nominal", "design_log_ratio": {"mean": round(mean, 5), "sd": round(sd, 5)},
            "note": "EFL / entrance pupil, as the lens is sold: the blur measures the real rays' cone "
                    "(f_number_effective), which a real lens's aberrations set apart from it; the ratio over "
                    f"published designs wide open (log-normal, mean {100 * mean:+.1f} %, sd {100 * sd:.1f} %) is "
                    "divided out and its spread carried in the interval. [lens] ideal = true in stack.toml declares "
                    "a lens without aberrations (a renderer's thin lens)"}


def apply(result: Any, ideal: bool) -> None:
    """Say in ``result`` (a ``FitResult``) which f-number it reports; unless the lens is ``ideal``,
    take every setting's f-number and aperture diameter to the nominal ones with the designs'
    spread, keeping the blur's own readings as ``f_number_effective`` and
    ``aperture_diameter_effective_mm``."""
    result.f_number_definition = definition(ideal)
    if ideal:
        return
    mean, sd = design_spread()
    for quantities in result.settings.values():
        n = quantities.get("f_number")
        if n is None or n.value is None:
            continue
        quantities["f_number_effective"] = n
        quantities["f_number"] = n.widened(sd, SOURCE, -mean)
        a = quantities.get("aperture_diameter_mm")
        if a is not None and a.value is not None:
            quantities["aperture_diameter_effective_mm"] = a  # (the real cone's: the Airy pattern's)
            quantities["aperture_diameter_mm"] = a.widened(sd, SOURCE, mean)
