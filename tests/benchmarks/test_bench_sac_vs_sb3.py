"""``benchmarks/sac_vs_sb3.py`` at toy sizes: both runs time the same window (skipped without stable-baselines3)."""

from __future__ import annotations

import json

import pytest
from _scripts import load_script

pytest.importorskip("stable_baselines3")

def _load_bench():
    return load_script("benchmarks/sac_vs_sb3.py")


def test_toy_run_times_equal_windows(tmp_path):
    out = tmp_path / "bench.json"
    result = _load_bench().main(["--steps", "20", "--learning-starts", "20", "--batch", "8", "--frames-per-batch",
                                 "10", "--rounds", "1", "--threads", "1", "--update-variants", "1", "--json", str(out),
                                 "loss.hidden=[16,16]", "env.horizon=30", "env.min_blocks=1", "env.max_blocks=1"])
    (only,) = result["threads"]["1"]["rounds"]
    for method in ("ours", "ours_bf16", "sb3"):
        run = only[method]
        assert run["steps"] == run["updates"] == run["sim_steps"] == 20  # one update per env step, both
        assert sum(run["split_s"].values()) == pytest.approx(run["seconds"])
    summary = result["threads"]["1"]["summary"]
    assert summary["ratio"]["median_of_rounds"] > 0 and summary["ratio_bf16"]["median_of_rounds"] > 0
    variants = json.loads(out.read_text())["threads"]["1"]["update_variants"]
    assert set(variants) == {"8", "16"} and all(v["sb3"]["sb3_over_this"] == 1 for v in variants.values())
