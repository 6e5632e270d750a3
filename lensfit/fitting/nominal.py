"""What a real lens's design does to the f-number and focal length a blur fit reads.

A blur-versus-depth fit measures the cone of the real rays: the spot's second moment grows with
the defocus as the real rays' spread of angles. A lens's f-number is paraxial, EFL over the
entrance pupil's diameter, what its aperture ring says. For an ideal lens (a renderer's thin-lens
camera) the two are the same; for a real one pupil aberrations, the non-paraxial angles of a fast
cone and the real best focus part them. The focal length moves too: it follows from the
calibrated pinhole distance S through ``1/S = 1/f - 1/(P X)``, which holds where the sensor sits
at the paraxial image, while a real lens is focused where its spot is smallest, which spherical
aberration moves off that image; S, and the f read, shift by the same share at every focus
distance, so no bracket can tell it from f.

Over 23 published designs wide open (optiland's sample objectives, the designs lensfit ships and
rayoptics's photographic samples: ``data_specs/f_number_survey.toml``, written by ``python -m
lensfit.bench.designs``) the focal length read ran 2.3 % short (a landscape lens at f/10) to
2.2 % long (an overcorrected patent design at f/4.5), most within 0.5 %; the f-number read (the
f read over the real cone's aperture) 2.2 % below to 6.4 % above EFL/EPD (a Petzval at f/1.4),
+1.2 % on average. Stopped down both shrink about fourfold per two stops.

So unless the lens is declared ideal (stack.toml ``[lens] ideal = true``, which synth writes for
its thin lens, or ``fit(..., ideal_lens=True)``):

- the f-number and aperture diameter reported are the nominal ones: the reading divided (the
  diameter multiplied) by the survey's ratio, a log-normal of the designs' mean and spread, the
  spread widened to the prediction interval of a new design from a sample of 23 (x 1.08) and
  further, until the 95 % interval holds every surveyed design (the ratios are skewed: 2.5 % in
  log wide open). The blur's own reading stays beside it as ``f_number_effective``;
- the focal lengths, a fitted P (a bracket reads it through the same S) and
  ``f_number_effective`` keep their values and carry the spread of the focal length read about
  zero (the shifts run both ways; 1.2 % wide open, enough to hold every surveyed design).

Each setting takes the survey's rows as far below full aperture as its f-number lies under the
lens's widest f-number where that is given (``[lens] widest_f_number``, which ``lensfit init``
copies from EXIF; up to three stops); without it, the spread wide open (the photographer's usual
case, and conservative stopped down).
"""

from __future__ import annotations

import functools
import math
import statistics
from typing import Any

#: The variance source the term carries in the error budget (results.json ``variance_shares``).
SOURCE = "lens_design"


#: The stops below full aperture the survey covers (``data_specs/f_number_survey.toml``): a
#: setting stopped down further carries the spread at the last.
SURVEY_STOPS = 3


@functools.cache
def _survey_logs(stops: int = 0) -> dict[str, list[float]]:
    """The survey's designs ``stops`` below full aperture: log N_effective / (EFL/EPD)
    (``"aperture"``: the real cone's aperture over the paraxial one, inverted), log f_read / EFL
    (``"focal"``) and their sum, log of the f-number the fit reads over the nominal one
    (``"f_number"``: its N is f_read / A)."""
    import tomllib

    from lensfit.io.specs import specs_dir

    rows = [r for r in tomllib.loads((specs_dir() / "f_number_survey.toml").read_text())["design"]
            if r["stops_down"] == stops]
    aperture = [math.log(r["ratio"]) for r in rows]
    focal = [math.log(r["focal_ratio"]) for r in rows]
    return {"aperture": aperture, "focal": focal, "f_number": [a + b for a, b in zip(aperture, focal)]}


def _spread(logs: list[float], centred: bool) -> tuple[float, float]:
    """Mean and spread a new design's log ratio has about the sample ``logs`` (n designs): the
    sample's standard deviation times ``t(0.975, n - 1) / z(0.975) * sqrt(1 + 1/n)`` (so that the
    Gaussian 95 % interval the fit states is the t prediction interval), and at least the largest
    distance of a surveyed design from the mean over z(0.975), so that the interval holds every
    design surveyed. ``centred``: about zero (mean 0, the root mean square for the deviation), for
    a term whose shifts run both ways and whose mean no correction should assume."""
    from scipy import stats

    n = len(logs)
    z = float(stats.norm.ppf(0.975))
    predictive = float(stats.t.ppf(0.975, n - 1) / z) * math.sqrt(1.0 + 1.0 / n)
    mean = 0.0 if centred else statistics.fmean(logs)
    deviation = math.sqrt(statistics.fmean([x * x for x in logs])) if centred else statistics.stdev(logs)
    # The ratios are skewed (most designs within 2 %, a fast Petzval +6.4 %): a Gaussian fitted to
    # them ends its 95 % interval inside the sample's own range, which holds a new design only 90 %
    # of the time ((n - 1) / (n + 1)). The spread is at least wide enough for the interval to hold
    # every surveyed design.
    return mean, max(deviation * predictive, max(abs(x - mean) for x in logs) / z)


def stops_down(f_number: float | None, widest_f_number: float | None) -> int:
    """Whole stops (factors of sqrt 2) ``f_number`` lies below the lens's full aperture, at most
    ``SURVEY_STOPS``; 0 where either is unknown. Rounded down (to the next wider survey row, whose
    spread is the larger) with a tenth of a stop's give for an f-number read a little open."""
    if not f_number or not widest_f_number or not math.isfinite(f_number):
        return 0
    return max(0, min(SURVEY_STOPS, math.floor(2.0 * math.log2(f_number / widest_f_number) + 0.1)))


@functools.cache
def design_spread(stops: int = 0) -> tuple[float, float]:
    """Mean and spread of log(N_read / (EFL/EPD)) over the survey's designs ``stops`` below full
    aperture: the f-number term (N_read is the focal length read over the real cone's aperture,
    so both parts move it)."""
    return _spread(_survey_logs(stops)["f_number"], centred=False)


@functools.cache
def aperture_spread(stops: int = 0) -> tuple[float, float]:
    """Mean and spread of log(EPD / A_real) over the survey's designs ``stops`` below full
    aperture: the aperture diameter's term."""
    return _spread(_survey_logs(stops)["aperture"], centred=False)


@functools.cache
def focal_spread(stops: int = 0) -> float:
    """Spread of log(f_read / EFL) about zero over the survey's designs ``stops`` below full
    aperture: the focal length's term (and the fitted P's, which a bracket reads through the same
    shifted ``S``)."""
    return _spread(_survey_logs(stops)["focal"], centred=True)[1]


def definition(ideal: bool, stops: dict[str, int] | None = None) -> dict[str, Any]:
    """results.json ``f_number_definition``: which f-number is reported, and how; ``stops``: how
    far below full aperture each setting is, where the lens's widest f-number is known."""
    if ideal:
        return {"reported": "effective", "design_log_ratio": None,
                "note": "an ideal lens (declared): the f-number is the blur's own, EFL / entrance pupil"}
    least = min(stops.values(), default=0) if stops else 0
    mean, sd = design_spread(least)
    sd_f = focal_spread(least)
    where = (f"{least} stop{'s' if least != 1 else ''} below full aperture, the widest setting" if least else
             "wide open" + ("" if stops else " (the lens's widest f-number not given: [lens] widest_f_number)"))
    out = {"reported": "nominal", "design_log_ratio": {"mean": round(mean, 5), "sd": round(sd, 5)},
           "focal_length_log_sd": round(sd_f, 5),
           "note": "EFL / entrance pupil, as the lens is sold: the blur measures the real rays' cone "
                   "(f_number_effective), which a real lens's aberrations set apart from it; the ratio over "
                   f"published designs {where} (log-normal, mean {100 * mean:+.1f} %, sd {100 * sd:.1f} %) is "
                   "divided out and its spread carried in the interval. The focal length, P and "
                   "f_number_effective carry the spread of the focal length a calibration reads with the sensor "
                   f"at a real lens's best focus, off its paraxial image (sd {100 * sd_f:.1f} % over the same "
                   "designs). [lens] ideal = true in stack.toml declares a lens without aberrations (a "
                   "renderer's thin lens)"}
    if stops:
        out["stops_down"] = dict(stops)
    return out


def apply(result: Any, ideal: bool, widest_f_number: float | None = None) -> None:
    """Say in ``result`` (a ``FitResult``) which f-number it reports; unless the lens is ``ideal``,
    take every setting's f-number and aperture diameter to the nominal ones with the designs'
    spread, keeping the blur's own readings as ``f_number_effective`` and
    ``aperture_diameter_effective_mm``, and carry the spread of the focal length read at the real
    best focus into the focal lengths, ``f_number_effective`` and a fitted P. Each setting takes
    the designs' spread as far below full aperture as its f-number lies under
    ``widest_f_number`` (wide open where that is unknown); what the settings share, the widest's."""
    stops = {label: stops_down(q["f_number"].value if q.get("f_number") else None, widest_f_number)
             for label, q in result.settings.items()} if widest_f_number else None
    result.f_number_definition = definition(ideal, stops)
    if ideal:
        return
    least = min(stops.values(), default=0) if stops else 0
    result.focal_length_mm = result.focal_length_mm.widened(focal_spread(least), SOURCE)
    if result.pupil_magnification_source == "fitted":
        result.pupil_magnification = result.pupil_magnification.widened(focal_spread(least), SOURCE)
    # A focal length the settings share (one setting, or a lens focusing as a unit) is read through
    # every setting's S, the widest's shift included: each setting carries the widest's term in f.
    shared = result.focal_length_mm.value is not None
    for label, quantities in result.settings.items():
        k = stops[label] if stops else 0
        mean, sd = design_spread(k)
        mean_a, sd_a = aperture_spread(k)
        sd_f = focal_spread(least if shared else k)
        if sd_f > focal_spread(k):  # (N = f / A: the shared f's term beyond the one at its own aperture)
            sd = math.hypot(sd, sd_f)
        f = quantities.get("focal_length_mm")
        if f is not None:
            quantities["focal_length_mm"] = f.widened(sd_f, SOURCE)
        n = quantities.get("f_number")
        if n is None or n.value is None:
            continue
        quantities["f_number_effective"] = n.widened(sd_f, SOURCE)
        quantities["f_number"] = n.widened(sd, SOURCE, -mean)
        a = quantities.get("aperture_diameter_mm")
        if a is not None and a.value is not None:
            quantities["aperture_diameter_effective_mm"] = a  # (the real cone's: the Airy pattern's)
            quantities["aperture_diameter_mm"] = a.widened(sd_a, SOURCE, mean_a)
