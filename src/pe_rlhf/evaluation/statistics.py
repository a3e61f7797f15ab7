"""Confidence intervals over seeds: the one place that says how the apps (sweeps, compare, claims) summarise seeds.

``bootstrap_interval(values)`` is ``[mean, lo, hi]``, a 95% bootstrap CI of the mean (scipy's BCa, 10,000
resamples, seeded; percentile with two seeds); ``iqm(values)`` the interquartile mean (25% trimmed mean) and
``iqm_interval(values)`` its interval, given only from :data:`IQM_MIN_SEEDS` seeds (fewer leave nothing to
trim); ``seed_stats(values)`` the dict the tables read: ``{mean, std, lo, hi, n}``. Non-finite values (a seed
without the metric) are dropped; with one seed, or when every seed agrees, ``lo == hi == mean``.
scipy rather than rliable: rliable's stratified bootstrap would add arch, statsmodels and seaborn to the pins.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

CONFIDENCE, RESAMPLES, SEED = 0.95, 10_000, 0
IQM_MIN_SEEDS = 5
TRIM = 0.25  # the IQM cuts a quarter off each end


def finite_values(values: Sequence[float | None]) -> np.ndarray:
    """The finite entries of ``values`` as a float array (None and NaN dropped)."""
    return np.asarray([float(v) for v in values if v is not None and math.isfinite(float(v))], dtype=float)


def iqm(values: Sequence[float | None]) -> float:
    """Interquartile mean of the finite values (``scipy.stats.trim_mean(x, 0.25)``); NaN without any."""
    from scipy.stats import trim_mean

    x = finite_values(values)
    return float(trim_mean(x, TRIM)) if len(x) else math.nan


def _mean(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


def _iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    from scipy.stats import trim_mean

    return trim_mean(x, TRIM, axis=axis)


def _interval(x: np.ndarray, statistic: Callable, method: str) -> tuple[float, float]:
    from scipy.stats import bootstrap

    res = bootstrap((x,), statistic, confidence_level=CONFIDENCE, n_resamples=RESAMPLES, method=method,
                    random_state=np.random.default_rng(SEED))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def bootstrap_interval(values: Sequence[float | None], statistic: Callable = _mean) -> list[float] | None:
    """``[stat, lo, hi]`` of the finite ``values``: ``statistic`` (vectorised, ``axis=``; default the mean) and
    its 95% bootstrap CI; None without finite values."""
    x = finite_values(values)
    if not len(x):
        return None
    point = float(statistic(x, axis=-1))
    if len(x) < 2 or np.ptp(x) == 0:
        return [point, point, point]
    lo, hi = _interval(x, statistic, "BCa" if len(x) >= 3 else "percentile")
    if not (math.isfinite(lo) and math.isfinite(hi)):  # BCa degenerates on tiny samples: fall back
        lo, hi = _interval(x, statistic, "percentile")
    return [point, lo, hi]


def iqm_interval(values: Sequence[float | None]) -> list[float] | None:
    """``[iqm, lo, hi]`` (95% bootstrap CI of the IQM), or None under :data:`IQM_MIN_SEEDS` finite values."""
    if len(finite_values(values)) < IQM_MIN_SEEDS:
        return None
    return bootstrap_interval(values, _iqm)


def seed_stats(values: Sequence[float | None]) -> dict[str, float]:
    """``{mean, std, lo, hi, n}`` over the finite values: mean, population std, the 95% CI of the mean
    (:func:`bootstrap_interval`) and how many; NaN (``n == 0``) without any."""
    x = finite_values(values)
    if not len(x):
        return {"mean": math.nan, "std": math.nan, "lo": math.nan, "hi": math.nan, "n": 0}
    mean, lo, hi = bootstrap_interval(x)
    return {"mean": mean, "std": float(np.std(x)), "lo": lo, "hi": hi, "n": len(x)}


def interval_text(stat: dict[str, float], fmt: str) -> str:
    """``mean [lo, hi]`` in ``fmt`` (one seed: its value; none: ``—``)."""
    if not stat["n"]:
        return "—"
    if stat["n"] == 1:
        return format(stat["mean"], fmt)
    return f"{stat['mean']:{fmt}} [{stat['lo']:{fmt}}, {stat['hi']:{fmt}}]"


__all__ = ["CONFIDENCE", "IQM_MIN_SEEDS", "bootstrap_interval", "finite_values", "interval_text", "iqm",
           "iqm_interval", "seed_stats"]
