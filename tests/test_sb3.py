"""``pe_rlhf.sb3``: SB3's off-policy learners store a takeover's executed action, the policy's elsewhere."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from pe_rlhf.mentors import Mentor, MentorDecision
from pe_rlhf.wrappers import InterventionWrapper

pytest.importorskip("stable_baselines3")
from pe_rlhf.sb3 import InterventionSAC, InterventionTD3  # noqa: E402

STEPS = 120


class PositiveTorqueMentor(Mentor):
    """Takes over whenever the agent's torque is positive and applies a fixed -1.5 N m (Pendulum's range: 2)."""

    name = "positive-torque"

    def act(self, env) -> np.ndarray:
        return np.array([-1.5], dtype=np.float32)

    def decide(self, env, agent_action) -> MentorDecision:
        return MentorDecision(bool(agent_action[0] > 0), self.act(env))


@pytest.mark.parametrize("learner", [InterventionSAC, InterventionTD3])
def test_the_buffer_holds_the_executed_action_of_each_takeover(learner, one_thread):
    env = InterventionWrapper(gym.make("Pendulum-v1"), PositiveTorqueMentor())
    reports = []

    def record(locals_, globals_):  # SB3's callback-as-function, after every env step
        info = locals_["infos"][0]
        reports.append((bool(info["is_intervention"]), float(info["agent_action"][0])))
        return True

    model = learner("MlpPolicy", env, learning_starts=STEPS + 1, buffer_size=STEPS, seed=0, device="cpu")
    model.learn(total_timesteps=STEPS, callback=record)
    stored = model.replay_buffer.actions[:STEPS, 0, 0]  # SB3's [-1, 1] units: torque / 2 on Pendulum
    taken = np.array([t for t, _ in reports])
    proposed = np.array([a for _, a in reports])
    assert 0.2 < taken.mean() < 0.8  # random warm-up actions: both kinds of step happen
    np.testing.assert_allclose(stored[taken], -0.75, rtol=1e-6)  # the mentor's -1.5 N m, scaled
    np.testing.assert_allclose(stored[~taken], proposed[~taken] / 2.0, rtol=1e-5)  # the agent's own, scaled
    assert (stored[~taken] <= 0).all() and not math.isclose(float(np.abs(proposed[~taken]).sum()), 0.0)
