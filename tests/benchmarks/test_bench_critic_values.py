"""``benchmarks/critic_values.py``: the steps-before-a-takeover count, and the table from a real run's checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
from _scripts import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("benchmarks/critic_values.py")


def test_steps_before_a_takeover_count_back_within_a_trajectory(bench):
    traj = np.array([0, 0, 0, 0, 1, 1, 1])
    before = np.array([0, 1, 0, 1, 0, 0, 1], dtype=bool)  # rows 1 and 3 of trajectory 0, row 6 of trajectory 1
    k = bench.steps_before_takeover(traj, before, reach=2)
    far = np.iinfo(np.int64).max
    assert k.tolist() == [2, 1, 2, 1, far, 2, 1]  # row 4 is 3 rows back: beyond reach


def test_a_runs_agent_rows_fall_into_the_bands_once_each(bench, tmp_path):
    runs = load_script("tests/reliability/_runs.py", "reliability_runs")
    out = tmp_path / "run"
    runs.train(out, "collector.total_frames=150", "collector.warmup_steps=25")
    (result,) = bench.main([str(out), "--step", "150", "--json", str(tmp_path / "v.json")])
    assert result["agent_rows"] + result["takeover_rows"] == 150
    assert sum(b["rows"] for b in result["bands"].values()) == result["agent_rows"] > 0
    assert all(np.isfinite(b["q_exec"]) and np.isfinite(b["q_pi"]) for b in result["bands"].values())
    assert 0 <= result["brake_preferred_share"] <= 1 and (tmp_path / "v.json").is_file()
    with pytest.raises(SystemExit):
        bench.main([str(out), "--step", "999"])
