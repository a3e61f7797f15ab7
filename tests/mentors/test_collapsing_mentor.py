"""CollapsingMentor: one preset until the switch step, the other after; steps counted once per env step;
state round trip; built by name and accepted by the recipe config (real simulator, no mocks)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from pe_rlhf.envs import make_gym_env, scene_seeds
from pe_rlhf.mentors import CollapsingMentor, make_mentor
from pe_rlhf.mentors.simulated import PRESETS, SimulatedMentor
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.algorithms.proxy_q.config import load_config

SWITCH = 6


@pytest.fixture(scope="module")
def env():
    env = make_gym_env({"split": "train", "horizon": 40})
    yield env
    env.close()


def _drive(env, mentor, steps: int, seed: int) -> list[np.ndarray]:
    """The mentor drives alone for ``steps`` env steps (calling ``act`` then ``decide`` on each, as a
    recording and a takeover might), resetting on episode ends; returns the executed actions."""
    env.reset(options={"scene_seed": seed})
    mentor.reset(env)
    actions = []
    for _ in range(steps):
        action = mentor.act(env)
        assert np.array_equal(mentor.decide(env, np.zeros(2, np.float32)).action, action)  # same step: counted once
        actions.append(action)
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset(options={"scene_seed": seed})
            mentor.reset(env)
    return actions


def test_switches_from_before_to_after_at_the_step(env):
    seed = scene_seeds("train")[0]
    collapsing = CollapsingMentor(switch_step=SWITCH, before="professional", after="adversarial", seed=3)
    actions = _drive(env, collapsing, SWITCH + 4, seed)
    assert collapsing.steps == SWITCH + 4 and collapsing.collapsed
    assert collapsing.active is collapsing.after and collapsing.after.profile == PRESETS["adversarial"]
    # the first SWITCH steps are exactly a professional's (same seed, same scene)
    professional = SimulatedMentor(PRESETS["professional"], seed=3, name="professional")
    reference = _drive(env, professional, SWITCH, seed)
    np.testing.assert_array_equal(np.stack(actions[:SWITCH]), np.stack(reference))


def test_state_round_trip_continues_identically(env):
    """Saved two steps before the switch, restored into a fresh mentor on the replayed scene: the next
    four actions (across the switch) are the same."""
    seed = scene_seeds("train")[1]
    a = make_mentor("collapsing", 5, switch_step=SWITCH)
    env.reset(options={"scene_seed": seed})
    a.reset(env)
    executed = []
    for _ in range(SWITCH - 2):
        executed.append(a.act(env))
        env.step(executed[-1])
    state = copy.deepcopy(a.state_dict())
    tail = []
    for _ in range(4):
        tail.append(a.act(env))
        env.step(tail[-1])
    assert a.collapsed
    b = make_mentor("collapsing", 5, switch_step=SWITCH)
    env.reset(options={"scene_seed": seed})
    for action in executed:
        env.step(action)
    b.load_state_dict(state)
    assert b.steps == SWITCH - 2 and not b.collapsed
    replay = []
    for _ in range(4):
        replay.append(b.act(env))
        env.step(replay[-1])
    np.testing.assert_array_equal(np.stack(replay), np.stack(tail))
    with pytest.raises(ValueError, match="switching at step"):
        make_mentor("collapsing", 5, switch_step=SWITCH + 1).load_state_dict(state)


@pytest.mark.parametrize("kwargs, field", [({"switch_step": -1}, "switch_step"), ({"switch_step": 1.5}, "switch_step"),
                                           ({"before": "expert"}, "before"), ({"after": "nobody"}, "after")])
def test_bad_arguments_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        CollapsingMentor(**kwargs)


def test_registry_and_recipe_config():
    with pytest.raises(ValueError, match="switch_at"):
        make_mentor("collapsing", 0, switch_at=10)
    cfg = load_config(None, ["profile=smoke", "mentor.name=collapsing", "mentor.kwargs.switch_step=150",
                             "mentor.kwargs.after=amateur"])
    assert cfg.mentor.kwargs.switch_step == 150
    with pytest.raises(ConfigError, match=r"mentor\.kwargs\.switch_at"):
        load_config(None, ["profile=smoke", "mentor.name=collapsing", "mentor.kwargs.switch_at=150"])
