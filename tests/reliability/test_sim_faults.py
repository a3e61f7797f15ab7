"""The simulator raises or returns NaN/inf mid-episode: the episode ends (truncated, ``sim_error``),
it is logged, and the run goes on; a simulator that keeps failing stops with a clear error."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from torchrl.collectors import Collector

from pe_rlhf.envs import make_gym_env
from pe_rlhf.envs.driving_env import MAX_CONSECUTIVE_SIM_ERRORS, DrivingEnv, SimulatorError
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.mentors import make_mentor
from pe_rlhf.algorithms.proxy_q.steps import batch_metrics
from pe_rlhf.transforms import InterventionTransform

CONFIG = {"split": "train", "horizon": 40, "min_blocks": 2, "max_blocks": 2}
pytestmark = pytest.mark.usefixtures("one_thread")


def inject(monkeypatch, faults: dict[int, str]) -> list[int]:
    """Make ``DrivingEnv._simulate`` fail on the given call numbers (``"raise"`` or ``"nan"``: the
    ego's position becomes NaN, so the observation does); returns the list of call numbers seen."""
    real = DrivingEnv._simulate
    calls: list[int] = []

    def simulate(self, action):
        calls.append(len(calls))
        kind = faults.get(len(calls) - 1)
        if kind == "raise":
            raise RuntimeError("highway-env blew up")
        if kind == "nan":
            self.vehicle.position = np.array([np.nan, np.nan])
        return real(self, action)

    monkeypatch.setattr(DrivingEnv, "_simulate", simulate)
    return calls


@pytest.mark.parametrize("kind", ["raise", "nan"])
def test_fault_ends_the_episode_truncated_with_the_last_good_observation(monkeypatch, caplog, kind):
    env = make_gym_env(CONFIG)
    obs0, _ = env.reset(options={"scene_seed": 3})
    inject(monkeypatch, {2: kind})
    for _ in range(2):
        obs, *_ = env.step(np.array([0.0, 0.5]))
    with caplog.at_level(logging.WARNING, logger="pe_rlhf.envs"):
        bad, reward, terminated, truncated, info = env.step(np.array([0.0, 0.5]))
    assert truncated and not terminated and reward == 0.0 and info["sim_error"] and info["cost"] == 0.0
    assert np.array_equal(bad, obs) and np.isfinite(bad).all()
    assert env.sim_errors == 1
    message = caplog.records[-1].getMessage()
    assert "scene 3 step 2: simulator fault" in message and ("blew up" in message or "non-finite" in message)
    env.reset(options={"scene_seed": 3})  # the next episode is a fresh scene: the run goes on
    obs, _, _, _, info = env.step(np.array([0.0, 0.5]))
    assert not info["sim_error"] and np.isfinite(obs).all()


def test_a_simulator_that_keeps_failing_stops_with_a_clear_error(monkeypatch):
    env = make_gym_env(CONFIG)
    inject(monkeypatch, {i: "raise" for i in range(100)})
    for _ in range(MAX_CONSECUTIVE_SIM_ERRORS - 1):
        env.reset()
        assert env.step(np.zeros(2))[4]["sim_error"]
    env.reset()
    with pytest.raises(SimulatorError, match=f"failed on {MAX_CONSECUTIVE_SIM_ERRORS} steps in a row.*blew up"):
        env.step(np.zeros(2))


def test_non_finite_action_is_the_callers_error():
    env = make_gym_env(CONFIG)
    env.reset()
    with pytest.raises(ValueError, match=r"action \[nan, 0.5\] is not finite"):
        env.step(np.array([np.nan, 0.5]))


def test_collector_with_interventions_runs_through_faults(monkeypatch):
    """Inside a TorchRL Collector (InterventionTransform, simulated mentor): faulty steps end their
    episodes, the collector resets and keeps collecting, the trainer's metrics count them."""
    env = make_env(CONFIG)
    env.append_transform(InterventionTransform(make_mentor("professional", seed=0)))
    env.set_seed(0)
    calls = inject(monkeypatch, {5: "raise", 12: "nan", 30: "raise"})
    collector = Collector(env, None, frames_per_batch=40, total_frames=40)  # random agent
    batch = next(iter(collector))
    collector.shutdown()
    nxt = batch["next"]
    errors = nxt["sim_error"].squeeze(-1)
    assert batch.numel() == 40 and len(calls) == 40
    assert errors.nonzero().squeeze(-1).tolist() == [5, 12, 30]
    assert nxt["truncated"][errors].all() and nxt["done"][errors].all()
    assert torch.isfinite(nxt["observation"]).all()
    assert batch_metrics(batch)["sim_errors"] == 3.0
    assert unwrap(env).sim_errors == 3
