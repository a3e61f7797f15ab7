"""pe_rlhf.evaluation.statistics: the intervals over seeds the sweep, compare and claims tables print."""

import math

import numpy as np
import pytest
from scipy.stats import trim_mean

from pe_rlhf.evaluation.statistics import (
    IQM_MIN_SEEDS,
    bootstrap_interval,
    interval_text,
    iqm,
    iqm_interval,
    seed_stats,
)


def test_two_seeds_give_their_range_and_agreeing_seeds_a_point():
    # resamples of two values have means in {a, (a+b)/2, b}: the 2.5% and 97.5% quantiles are a and b
    assert bootstrap_interval([0.2, 0.4]) == pytest.approx([0.3, 0.2, 0.4])
    assert bootstrap_interval([0.7, 0.7, 0.7]) == pytest.approx([0.7, 0.7, 0.7])
    assert bootstrap_interval([5.0]) == [5.0, 5.0, 5.0]
    assert bootstrap_interval([float("nan"), None]) is None


def test_interval_brackets_the_mean_is_seeded_and_ignores_missing_seeds():
    values = [0.1, 0.5, 0.4, 0.9, 0.3]
    mean, lo, hi = bootstrap_interval(values)
    assert mean == pytest.approx(np.mean(values)) and min(values) <= lo < mean < hi <= max(values)
    assert bootstrap_interval(values + [float("nan"), None]) == [mean, lo, hi]  # same draws: seeded


def test_iqm_is_the_25_percent_trimmed_mean():
    values = [1.0, 2.0, 3.0, 4.0, 100.0, 6.0, 7.0, 8.0]
    assert iqm(values) == pytest.approx(trim_mean(values, 0.25))
    assert iqm(values) == pytest.approx(np.mean([3.0, 4.0, 6.0, 7.0]))  # the middle half: the outlier is cut
    assert iqm([2.0, float("nan"), 4.0]) == 3.0 and math.isnan(iqm([]))


def test_iqm_interval_only_from_five_seeds():
    assert IQM_MIN_SEEDS == 5
    assert iqm_interval([1.0, 2.0, 3.0, 4.0]) is None
    values = [1.0, 2.0, 3.0, 4.0, 100.0, 6.0, 7.0, 8.0]
    point, lo, hi = iqm_interval(values)
    assert point == pytest.approx(iqm(values)) and lo <= point <= hi < 100.0  # robust: the outlier barely moves it
    assert iqm_interval([3.0] * 5) == [3.0, 3.0, 3.0]


def test_seed_stats_and_their_text():
    stat = seed_stats([1.0, float("nan"), 3.0])
    assert stat == {"mean": 2.0, "std": 1.0, "lo": 1.0, "hi": 3.0, "n": 2}
    assert interval_text(stat, ".2f") == "2.00 [1.00, 3.00]"
    assert interval_text(seed_stats([0.25]), ".2f") == "0.25"  # one seed: no interval
    assert interval_text(seed_stats([None]), ".2f") == "—"


def test_claims_still_export_the_interval():
    from pe_rlhf.apps.sweeps import claims

    assert claims.bootstrap_interval is bootstrap_interval


def test_sweep_summary_error_bars_are_the_interval():
    from pe_rlhf.apps.sweeps.plots import _bars, _ci_yerr, _pyplot

    rows = [{"method": "pe-rlhf", "mentor": "-", "success_rate": seed_stats([0.2, 0.4, 0.9])},
            {"method": "idm-mobil", "mentor": "-", "success_rate": seed_stats([])}]
    stat = rows[0]["success_rate"]
    assert _ci_yerr([stat, rows[1]["success_rate"]]) == [[stat["mean"] - stat["lo"], 0.0],
                                                         [stat["hi"] - stat["mean"], 0.0]]
    plt = _pyplot()
    fig, ax = plt.subplots()
    _bars(ax, rows, "success_rate")
    (segments,) = [c.get_segments() for c in ax.collections]  # the error bar's vertical line
    assert [segments[0][0][1], segments[0][1][1]] == pytest.approx([stat["lo"], stat["hi"]])
    plt.close(fig)
