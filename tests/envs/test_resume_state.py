"""``DrivingEnv.resume_state``: a mid-episode env, as JSON, continued by another env exactly; physics' plan too."""

from __future__ import annotations

import json

import numpy as np
from _factories import FAST_CONFIG

from pe_rlhf.envs.driving_env import DrivingEnv
from pe_rlhf.physics import IDMMobilPolicy


def _drive(env, physics, steps):
    """``steps`` physics-driven steps (a new episode where one ends); the observations and rewards."""
    out = []
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(physics(env))
        out.append((obs, reward))
        if terminated or truncated:
            env.reset()
    return out


def test_a_resumed_env_and_physics_continue_exactly_as_the_originals():
    env, physics = DrivingEnv(FAST_CONFIG), IDMMobilPolicy()
    env.reset(seed=3)
    _drive(env, physics, 23)  # mid-episode, a lane plan under way
    state = json.loads(json.dumps({"env": env.resume_state(), "physics": physics.state_dict(env)}))
    assert len(state["env"]["actions"]) == 23 and state["physics"]["planning"]

    other, other_physics = DrivingEnv(FAST_CONFIG), IDMMobilPolicy()
    other.reset(seed=99)  # another scene RNG and scene: the state replaces both
    other.load_resume_state(state["env"])
    other_physics.load_state_dict(state["physics"])
    assert other.scene_seed == env.scene_seed and other.steps == env.steps
    ahead, resumed = _drive(env, physics, 80), _drive(other, other_physics, 80)  # past the episode's end
    for (obs, reward), (obs2, reward2) in zip(ahead, resumed):
        assert np.array_equal(obs, obs2) and reward == reward2
    assert other.scene_seed == env.scene_seed  # the next episode's scene: the same draw


def test_physics_plan_of_another_episode_is_not_carried_over():
    env, physics = DrivingEnv(FAST_CONFIG), IDMMobilPolicy()
    env.reset(seed=0)
    physics(env)
    env.reset()  # a new road: the plan belongs to the last episode
    assert not physics.state_dict(env)["planning"]
    assert IDMMobilPolicy().state_dict() == {"target_lane": None, "planning": False, "last_decision": None}
