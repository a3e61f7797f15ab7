"""Issue 45, case 4: a non-finite observation at reset never leaves the env, a poisoned row that reached the buffer
is dropped on ``--resume``, and the loss's stop message says what will actually work.

Before: ``DrivingEnv.reset`` returned a NaN observation unchecked (``step`` checked); the row and the actor's NaN
action reached the buffer, the run stopped with ``FloatingPointError`` advising ``--resume``, and every resume
stopped again on the same row.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from _runs import checkpoint_contents, train

from pe_rlhf.envs import driving_env, make_gym_env
from pe_rlhf.envs.driving_env import SimulatorError
from pe_rlhf.runtime.checkpoint import find_checkpoint
from pe_rlhf.algorithms.proxy_q.trainer import ProxyQLearner

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]
CONFIG = {"split": "train", "horizon": 40, "min_blocks": 2, "max_blocks": 2}


def nan_at_reset(monkeypatch, which: set[int]) -> list[int]:
    """The first observation of the resets numbered in ``which`` (0 first) becomes NaN, inside ``reset``."""
    real, resets = driving_env.build_observation, []

    def build(env):
        obs = real(env)
        if env.time == 0 and env.steps == 0:  # a reset's observation, not a step's
            resets.append(len(resets))
            if resets[-1] in which:
                obs = np.full_like(obs, np.nan)
        return obs

    monkeypatch.setattr(driving_env, "build_observation", build)
    return resets


def test_a_non_finite_first_observation_draws_another_scene(monkeypatch, caplog):
    env = make_gym_env(CONFIG)
    nan_at_reset(monkeypatch, {0})
    with caplog.at_level(logging.WARNING, logger="pe_rlhf.envs"):
        obs, info = env.reset(seed=0)
    assert np.isfinite(obs).all() and env.unwrapped.sim_errors == 1
    assert "reset: simulator fault (observation has" in caplog.records[-1].getMessage()
    first = caplog.records[-1].getMessage().split()[1]
    assert str(info["scene_seed"]) != first  # another scene, not the faulty one again


def test_a_given_scene_that_starts_non_finite_is_a_clear_error(monkeypatch):
    env = make_gym_env(CONFIG)
    nan_at_reset(monkeypatch, {0, 1, 2, 3, 4, 5})
    with pytest.raises(SimulatorError, match="scene 3: the simulator's first observation is not finite"):
        env.reset(options={"scene_seed": 3})


def test_a_poisoned_row_is_dropped_on_resume_and_the_stop_message_says_so(tmp_path, monkeypatch, capsys):
    real = ProxyQLearner.store

    def store(self, item):  # a NaN observation reaches the buffer after warm-up (row 80)
        batch, journaled = item
        if int(self.counters.frames) == 75:
            batch = batch.clone()
            batch["observation"][5] = float("nan")
        return real(self, (batch, journaled))

    monkeypatch.setattr(ProxyQLearner, "store", store)
    out = tmp_path / "run"
    with pytest.raises(FloatingPointError) as stopped:
        train(out, "collector.total_frames=200")
    message = str(stopped.value)
    assert "not finite" in message and f"--resume {out}` drops the replay rows holding NaN" in message
    assert "optim.lr=<lower>" in message
    monkeypatch.setattr(ProxyQLearner, "store", real)
    capsys.readouterr()
    final = train(out, resume=True)
    assert "dropped 1 row(s) holding NaN or inf from replay buffer 'replay'" in capsys.readouterr().out
    assert final["training"]["frames"] == 200
    replay = checkpoint_contents(find_checkpoint(out / "checkpoints"))["replay"]
    assert len(replay) == 199
    for key, value in replay.items(include_nested=True, leaves_only=True):
        if value.is_floating_point():
            assert torch.isfinite(value).all(), key
