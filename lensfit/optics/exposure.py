"""The exposure triangle: exposure value and the equivalent shutter time, f-number and ISO
(part of the ``lensfit.optics`` API, which re-exports these functions; same conventions: NumPy
for NumPy/Python inputs, ``jax.numpy`` for JAX inputs, float64, validated arguments).

References: S. F. Ray, *Applied Photographic Optics*, 3rd ed., Focal Press 2002, ch. 8; ISO 2720.
"""

from __future__ import annotations

from lensfit.optics.checks import arg, float64, namespace

__all__ = ["exposure_value", "equivalent_shutter_s", "equivalent_f_number", "equivalent_iso"]


@float64
def exposure_value(f_number, shutter_s, iso=100.0):
    """Exposure value of camera settings, referred to ISO 100.

    .. math:: \\mathrm{EV}_{100} = \\log_2\\frac{N^2}{t} - \\log_2\\frac{S}{100}

    Settings with the same EV_100 give the same image brightness (same scene luminance).
    At ISO 100 this is the classic ``EV = log2(N^2/t)``: f/1 at 1 s is EV 0.

    Parameters
    ----------
    f_number : array_like
        f-number N, > 0.
    shutter_s : array_like
        Exposure (shutter) time t, seconds, > 0.
    iso : array_like, optional
        ISO speed S, > 0. Default 100.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        EV_100 (stops).

    References
    ----------
    ISO 2720:1974; Wikipedia, "Exposure value" (EV table).

    Examples
    --------
    >>> float(exposure_value(1.0, 1.0))
    0.0
    >>> round(float(exposure_value(16.0, 1 / 100, 100)), 3)   # sunny 16 at ISO 100
    14.644
    """
    N = arg("f_number", f_number, positive=True)
    t = arg("shutter_s", shutter_s, positive=True)
    S = arg("iso", iso, positive=True)
    xp = namespace(N, t, S)
    return xp.log2(N * N / t) - xp.log2(S / 100.0)


@float64
def equivalent_shutter_s(f_number, shutter_s, iso, new_f_number, new_iso):
    """Shutter time that keeps the exposure when f-number and ISO change.

    .. math:: t' = t \\left(\\frac{N'}{N}\\right)^2 \\frac{S}{S'}

    Parameters
    ----------
    f_number, shutter_s, iso : array_like
        Reference settings (N, t in seconds, S), all > 0.
    new_f_number, new_iso : array_like
        New f-number N' and ISO S', > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        New shutter time t', seconds.

    Examples
    --------
    >>> float(equivalent_shutter_s(8.0, 1 / 125, 100, 4.0, 100)) * 500
    1.0
    """
    N = arg("f_number", f_number, positive=True)
    t = arg("shutter_s", shutter_s, positive=True)
    S = arg("iso", iso, positive=True)
    N2 = arg("new_f_number", new_f_number, positive=True)
    S2 = arg("new_iso", new_iso, positive=True)
    return t * (N2 / N) ** 2 * (S / S2)


@float64
def equivalent_f_number(f_number, shutter_s, iso, new_shutter_s, new_iso):
    """f-number that keeps the exposure when shutter time and ISO change.

    .. math:: N' = N \\sqrt{\\frac{t'}{t} \\frac{S'}{S}}

    Parameters
    ----------
    f_number, shutter_s, iso : array_like
        Reference settings (N, t in seconds, S), all > 0.
    new_shutter_s, new_iso : array_like
        New shutter time t' (seconds) and ISO S', > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        New f-number N'.

    Examples
    --------
    >>> float(equivalent_f_number(8.0, 1 / 125, 100, 1 / 500, 100))
    4.0
    """
    N = arg("f_number", f_number, positive=True)
    t = arg("shutter_s", shutter_s, positive=True)
    S = arg("iso", iso, positive=True)
    t2 = arg("new_shutter_s", new_shutter_s, positive=True)
    S2 = arg("new_iso", new_iso, positive=True)
    return N * namespace(N, t, t2, S, S2).sqrt((t2 / t) * (S2 / S))


@float64
def equivalent_iso(f_number, shutter_s, iso, new_f_number, new_shutter_s):
    """ISO that keeps the exposure when f-number and shutter time change.

    .. math:: S' = S \\left(\\frac{N'}{N}\\right)^2 \\frac{t}{t'}

    Parameters
    ----------
    f_number, shutter_s, iso : array_like
        Reference settings (N, t in seconds, S), all > 0.
    new_f_number, new_shutter_s : array_like
        New f-number N' and shutter time t' (seconds), > 0.

    Returns
    -------
    numpy.ndarray or jax.Array (as the inputs)
        New ISO S'.

    Examples
    --------
    >>> float(equivalent_iso(8.0, 1 / 125, 100, 8.0, 1 / 500))
    400.0
    """
    N = arg("f_number", f_number, positive=True)
    t = arg("shutter_s", shutter_s, positive=True)
    S = arg("iso", iso, positive=True)
    N2 = arg("new_f_number", new_f_number, positive=True)
    t2 = arg("new_shutter_s", new_shutter_s, positive=True)
    return S * (N2 / N) ** 2 * (t / t2)
