"""``benchmarks/ensemble_selection.py``: importable, and the hybrid's extremes are the mentor's and physics'."""

from __future__ import annotations

import json

import pytest
from _scripts import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("benchmarks/ensemble_selection.py")


def test_extreme_thresholds_execute_the_mentor_or_physics(bench, tmp_path):
    # one scene holds every case: on train scene 11 the professional takes over 28% of IDM-MOBIL's steps (scene 0:
    # none), and IDM-MOBIL finishes it (scenes 1-4 time out behind obstacles: 4 times the steps)
    rows = bench.main(["--mentors", "professional", "--scenes", "11-11", "--epsilons", "-1000000", "1000000",
                       "--json", str(tmp_path / "floor.json")])
    by_row = {r["row"]: r for r in rows}
    alone, as_is = by_row["idm-mobil"], by_row["as-is"]
    always_mentor, always_physics = by_row["hybrid eps=-1e+06 margin=none"], by_row["hybrid eps=1e+06 margin=none"]
    assert alone["takeover_share"] == 0 and as_is["takeover_share"] > 0 and as_is["mentor_share"] == 1.0
    assert always_mentor["mentor_share"] == 1.0 and always_physics["mentor_share"] == 0.0
    # executing the mentor at every takeover step is the as-is run, step for step
    assert always_mentor["per_episode"] == as_is["per_episode"]
    # --resume keeps the saved rows of the same scenes and measures nothing again (a marker survives)
    saved = json.loads((tmp_path / "floor.json").read_text())
    saved["results"][1]["success"] = 0.123
    (tmp_path / "floor.json").write_text(json.dumps(saved))
    again = bench.main(["--mentors", "professional", "--scenes", "11-11", "--epsilons", "-1000000", "1000000",
                        "--json", str(tmp_path / "floor.json"), "--resume"])
    assert [r["row"] for r in again] == [r["row"] for r in rows] and again[1]["success"] == 0.123


def test_takeover_rates_watch_each_driver(bench):
    (row,) = bench.takeover_rates(["professional"], ["random"], [0])
    assert row["driver"] == "random" and 0.5 < row["takeover_share"] <= 1.0 and row["mentor_share"] == 1.0


def test_warmup_rows_the_mentor_drives_every_step_and_an_extreme_threshold_keeps_it(bench):
    rows = bench.warmup_rows(["professional"], [0], "train", "forecast", [-1e6])  # one scene: the mentor drives all
    alone, judged = rows
    assert alone["row"] == "warmup" and alone["takeover_share"] == 1.0 and alone["mentor_share"] == 1.0
    # a threshold no forecast can beat executes the mentor at every step: the paper's warm-up, step for step
    assert judged["mentor_share"] == 1.0 and judged["per_episode"] == alone["per_episode"]
