"""``benchmarks/selector_accuracy.py`` on a smoke PE-RLHF run: counterfactual labels and consistent counts."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from _scripts import load_pe_rlhf_recipe, load_script

from pe_rlhf.envs import make_gym_env
from pe_rlhf.physics import IDMMobilPolicy, PhysicsConfig
from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.algorithms.proxy_q.builders import build_physics


def test_selector_accuracy_on_a_smoke_run(tmp_path):
    run = tmp_path / "run"
    load_pe_rlhf_recipe().main(
        ["profile=smoke", "eval.video=false", "--out", str(run)])
    bench = load_script("benchmarks/selector_accuracy.py")
    out = tmp_path / "acc.json"
    (result,) = bench.main([str(run), "--scenes", "0-1", "--max-states", "12", "--every", "1", "--horizon", "20",
                            "--epsilons", "-1000", "1000", "--json", str(out)])
    assert json.loads(out.read_text())["results"][0]["takeover_states"] == result["takeover_states"]
    assert 1 <= result["takeover_states"] <= 12
    n, decisive = result["takeover_states"], result["decisive_states"]
    assert result["both_fail"] <= min(result["mentor_fails"], result["physics_fails"])
    assert decisive == result["mentor_fails"] + result["physics_fails"] - 2 * result["both_fail"] <= n
    assert (decisive == 0) == (result["decisive_events"] == 0) and result["decisive_events"] <= decisive
    # an epsilon below every advantage always picks the mentor, one above always picks physics
    if decisive:
        assert result["selector_right"]["-1000.0"] == pytest.approx(result["always_mentor_right"])
        assert result["selector_right"]["1000.0"] == pytest.approx(1 - result["always_mentor_right"])


def test_haco_run_is_refused(tmp_path):
    run = tmp_path / "haco"
    load_pe_rlhf_recipe().main(
        ["profile=smoke", "eval.video=false", "physics.enabled=false", "--out", str(run)])
    bench = load_script("benchmarks/selector_accuracy.py")
    with pytest.raises(SystemExit, match="no ensemble"):
        bench.main([str(run), "--max-states", "1"])


def test_every_below_one_is_refused(capsys):
    with pytest.raises(SystemExit):
        load_script("benchmarks/selector_accuracy.py").main(["no-such-run", "--every", "0"])
    assert "--every 0: must be at least 1" in capsys.readouterr().err


def test_the_executed_continuation_is_a_drivers_own_at_the_extreme_thresholds():
    """``--continuation executed``: with a threshold below every advantage the hybrid executes the mentor at every
    step (its own continuation), above every advantage physics: the same outcomes as ``fails`` with that driver."""
    bench = load_script("benchmarks/selector_accuracy.py")
    cfg, forecast = bench.expert_setup("adversarial", "forecast")
    env = make_gym_env(driving_config(cfg))
    obs, _ = env.reset(options={"scene_seed": 0})
    mentor, physics = build_mentor(cfg), build_physics(cfg)
    mentor.reset(env)
    physics.reset()
    oracle = IDMMobilPolicy(PhysicsConfig(see_obstacles=True))
    for proposer, fails_alone in ((mentor, False), (SteersOff(), True)):  # the adversarial preset, a driver that exits
        for eps, driver in ((-math.inf, proposer.act), (math.inf, physics)):
            action = np.asarray(driver(env), np.float32)
            executed = bench.fails_executed(env, obs, action, proposer, physics, forecast, eps, 15, 30, oracle)
            assert executed == bench.fails(env, action, driver, 15, 30, oracle)
            assert executed == (fails_alone and eps < 0)  # physics' continuation keeps the car on the road


class SteersOff:
    """A proposer that holds full steer and throttle: off the road within the hold."""

    def act(self, env):
        return np.array([1.0, 1.0], np.float32)
