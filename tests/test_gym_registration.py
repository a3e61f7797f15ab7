"""gymnasium's habits: ``import pe_rlhf`` registers ``pe_rlhf/Driving-v0`` (with a ``TimeLimit``, without loading
the simulator), and ``InterventionWrapper`` passes ``check_env`` with every shipped mentor, which needs
``reset(seed=)`` to reseed the mentor (and, in PE-RLHF, start the selector afresh): same seed, same actions, same
episode, whatever ran before."""

from __future__ import annotations

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import pe_rlhf
from pe_rlhf.envs import DrivingConfig
from pe_rlhf.mentors import make_mentor
from pe_rlhf.physics import IDMMobilPolicy, SafetyForecastConfig, SafetyForecastValue
from pe_rlhf.transforms import HybridActionSelector
from pe_rlhf.wrappers import InterventionWrapper

pytestmark = pytest.mark.usefixtures("one_thread_module")

# Every mentor make_mentor ships ("bad" is an alias of "adversarial"); the collapsing one switches at step 3, so
# that check_env's steps see both of its drivers; the human one has nobody at the keys (the agent drives).
MENTORS = {"professional": {}, "amateur": {}, "adversarial": {}, "collapsing": {"switch_step": 3}, "human": {}}
SMALL = {"traffic_density": 0.3, "obstacle_density": 0.5, "min_blocks": 2, "max_blocks": 2, "horizon": 60}


def test_import_pe_rlhf_registers_the_env_without_loading_the_simulator():
    code = ("import sys, pe_rlhf, gymnasium as gym; spec = gym.spec('pe_rlhf/Driving-v0'); "
            "print(spec.max_episode_steps, spec.entry_point, 'highway_env' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == [str(DrivingConfig().horizon), "pe_rlhf.envs.driving_env:DrivingEnv", "False", "False"]


def test_make_gives_a_time_limit_at_the_default_horizon():
    assert pe_rlhf.MAX_EPISODE_STEPS == DrivingConfig().horizon
    env = gym.make(pe_rlhf.ENV_ID, config=SMALL)
    assert isinstance(env, gym.wrappers.TimeLimit) and env.spec.max_episode_steps == pe_rlhf.MAX_EPISODE_STEPS
    longer = gym.make(pe_rlhf.ENV_ID, config={**SMALL, "horizon": 2000}, max_episode_steps=2000)
    assert longer.spec.max_episode_steps == 2000
    env.close(), longer.close()


def check_quietly(env) -> None:
    """``check_env``; the only warnings allowed: the env is wrapped, the action box is not [-1, 1]."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_close_check=True)
    messages = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert all("different from the unwrapped" in m or "symmetric and normalized" in m for m in messages), messages


@pytest.mark.parametrize("name", list(MENTORS))
def test_check_env_passes_on_the_wrapper_with_each_shipped_mentor(name):
    env = InterventionWrapper(gym.make(pe_rlhf.ENV_ID, config=SMALL), make_mentor(name, seed=0, **MENTORS[name]))
    check_quietly(env)
    env.close()


def pe_rlhf_wrapper(mentor: str) -> InterventionWrapper:
    """The recipe's selector: the physics forecast, epsilon -0.5 s, three vetoes before physics takes the wheel."""
    selector = HybridActionSelector(SafetyForecastValue(SafetyForecastConfig()), epsilon_select=-0.5,
                                    veto_patience=3)
    return InterventionWrapper(gym.make(pe_rlhf.ENV_ID, config=SMALL), make_mentor(mentor, seed=0),
                               physics=IDMMobilPolicy(), selector=selector)


def test_check_env_passes_with_physics_and_the_selector():
    check_quietly(pe_rlhf_wrapper("adversarial"))


def episode(env: InterventionWrapper, seed: int, steps: int = 40) -> list[tuple]:
    """Observations and takeover reports of ``steps`` steps after ``reset(seed=seed)``, fixed agent actions."""
    obs, _ = env.reset(seed=seed)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(steps, 2)).astype(np.float32)
    out = [(obs,)]
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        out.append((obs, reward, info["intervention"], info["teleop_action"], info["mentor_action"]))
        if terminated or truncated:
            break
    return out


@pytest.mark.parametrize("mentor", ["amateur", "adversarial"])
def test_a_seeded_reset_replays_the_episode_whatever_ran_before(mentor):
    """The mentor's noise, errors and fatigue start over at ``reset(seed=)``."""
    env = pe_rlhf_wrapper(mentor)
    first = episode(env, seed=5)
    episode(env, seed=11)  # advances the mentor's RNG and fatigue, and the selector's state
    again = episode(env, seed=5)
    assert len(first) == len(again)
    for a, b in zip(first, again):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    assert any(step[2] for step in first[1:])  # the mentor did take over: its actions were compared
