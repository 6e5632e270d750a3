"""Checks shared by the test modules (importable because pytest puts tests/ on sys.path)."""

from __future__ import annotations


def assert_recovered_or_refused(result, truth: dict[str, float], rel: float, k_sigma: float | None = None,
                                setting: str = "a") -> None:
    """Each quantity of ``truth`` (name -> true value) is within ``rel`` of the truth (and within
    ``k_sigma`` stated sigmas, when given), or is refused with a reason: never a silent number."""
    est = result.settings[setting]
    for q, t in truth.items():
        e = est[q]
        if e.value is None:
            assert e.reason, q
            continue
        assert abs(e.value / t - 1) < rel, (q, e.value, t)
        if k_sigma is not None:
            assert abs(e.value - t) < k_sigma * e.sigma + 1e-6 * t, (q, e.value, t, e.sigma)
