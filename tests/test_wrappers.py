"""``InterventionWrapper`` (gymnasium) decides as ``InterventionTransform`` (TorchRL); ``InfoToTakeoverKeys``
reads its info back into the transform's keys; ``pe_rlhf/Driving-v0`` passes gymnasium's ``check_env``.

Equivalence is step for step, with the same agent actions and seeds: on ``Pendulum-v1`` with a scripted
mentor written here, and on the driving env with the simulated professional mentor (and, in PE-RLHF mode,
IDM-MOBIL physics and a hybrid selector).
"""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from _factories import FAST_CONFIG, DriverMentor
from gymnasium.utils.env_checker import check_env
from torchrl.envs import GymEnv, GymWrapper, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from pe_rlhf.envs import ENV_ID, TRAIN_SEEDS, make_gym_env, register
from pe_rlhf.envs.torchrl_env import make_env
from pe_rlhf.mentors import Mentor, MentorDecision, make_mentor
from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.transforms import HybridActionSelector, InterventionTransform, takeover_cost
from pe_rlhf.transforms.intervention import OUT_KEYS
from pe_rlhf.wrappers import INFO_KEY, InfoToTakeoverKeys, InterventionWrapper

pytestmark = pytest.mark.usefixtures("one_thread_module")

LARGE = 1.0  # [N m] the scripted mentor takes over a Pendulum torque above this


class LargeTorqueMentor(Mentor):
    """Pendulum's scripted mentor: takes over when ``|torque| > LARGE``; its own action is a PD law towards
    upright (the true state ``env.state`` of ``PendulumEnv``), clipped to the torque range."""

    name = "large-torque"

    def __init__(self):
        self.resets = 0

    def reset(self, env) -> None:
        self.resets += 1

    def act(self, env) -> np.ndarray:
        th, thd = env.state
        th = (th + math.pi) % (2 * math.pi) - math.pi
        return np.clip([-3.0 * th - 0.8 * thd], -2.0, 2.0).astype(np.float32)

    def decide(self, env, agent_action) -> MentorDecision:
        return MentorDecision(bool(np.abs(agent_action).max() > LARGE), self.act(env))


def _pendulum_physics(env) -> np.ndarray:
    """A second controller (the 'physics' proposal): damping only."""
    return np.array([-0.5 * env.state[1]], dtype=np.float32).clip(-2.0, 2.0)


def _selector(obs_dim, action_dim, epsilon):
    torch.manual_seed(0)
    return HybridActionSelector(QEnsemble(obs_dim, action_dim, num_members=2, hidden=(16,)), epsilon_select=epsilon)


def _pendulum_actions(steps, seed=0):
    """Torques in [-2, 2]: about half above ``LARGE`` (takeovers), in runs so that takeovers start and end."""
    rng = np.random.default_rng(seed)
    scale = np.repeat(rng.choice([0.5, 2.0], size=steps // 5 + 1), 5)[:steps]
    return (rng.uniform(-1, 1, size=(steps, 1)) * scale[:, None]).astype(np.float32)


def _driving_actions(steps, seed=0):
    """``[steering, throttle]``: 8-step runs of mild driving (straight, some throttle) and random actions."""
    rng = np.random.default_rng(seed)
    mild = np.array([0.0, 0.3]) + rng.normal(0.0, 0.05, size=(steps, 2))
    wild = rng.uniform(-1.0, 1.0, size=(steps, 2))
    is_wild = (np.arange(steps) // 8) % 2 == 1
    return np.where(is_wild[:, None], wild, mild).clip(-1, 1).astype(np.float32)


# -- step loops: one for each face, over fixed agent actions; on an episode end the next reset ----------
def _torchrl_records(env, actions, resets):
    """``OUT_KEYS`` and the observation of each step of a TorchRL env; ``resets``: kwargs of each reset."""
    resets = iter(resets)
    td, records = env.reset(**next(resets)), []
    for a in actions:
        td["action"] = torch.as_tensor(a)
        td = env.step(td)
        nxt = td["next"]
        records.append({key: nxt[key].numpy().copy() for key in (*OUT_KEYS, "observation")})
        records[-1]["agent_action"] = td["action"].numpy().copy()
        td = env.reset(**next(resets)) if nxt["done"].item() else step_mdp(td)
    return records


def _gym_records(env, actions, resets):
    """The same records from an ``InterventionWrapper``'s info (flags and cost as ``(1,)`` arrays)."""
    resets = iter(resets)
    env.reset(**next(resets))
    records = []
    for a in actions:
        obs, _, terminated, truncated, info = env.step(a)
        rec = {key: np.atleast_1d(np.asarray(info.get(INFO_KEY[key], 0.0))) for key in OUT_KEYS}
        if "physics_action" not in info:
            rec["physics_action"] = np.zeros_like(rec["mentor_action"])
        records.append({**rec, "observation": obs.copy(), "agent_action": info["agent_action"]})
        if terminated or truncated:
            env.reset(**next(resets))
    return records


def _assert_same(records, expected):
    assert len(records) == len(expected)
    for t, (got, want) in enumerate(zip(records, expected)):
        for key, value in want.items():
            np.testing.assert_array_equal(np.asarray(got[key], value.dtype), value, err_msg=f"step {t}, {key}")


def _flags(records, key):
    return np.array([bool(r[key][0]) for r in records])


# -- the wrapper on Pendulum ------------------------------------------------------------------------------
def test_wrapper_executes_the_agent_or_the_mentor_and_reports_gym_hil_keys():
    env = InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor())
    env.reset(seed=0)
    small, large = np.array([0.5], np.float32), np.array([1.8], np.float32)
    for step, action in enumerate([small, large, large, small, large]):
        th, thd = env.unwrapped.state
        expected_mentor = LargeTorqueMentor().act(env.unwrapped)
        _, _, _, _, info = env.step(action)
        taken = bool(abs(action[0]) > LARGE)
        assert info["is_intervention"] is taken and info["intervention"] is taken
        assert info["mentor_selected"] is taken
        np.testing.assert_array_equal(info["mentor_action"], expected_mentor)
        executed = expected_mentor if taken else action
        np.testing.assert_array_equal(info["teleop_action"], executed)
        assert info["teleop_action"].dtype == np.float32 and info["teleop_action"].shape == (1,)
        np.testing.assert_array_equal(info["agent_action"], action)
        assert info["intervention_start"] is (step in (1, 4))
        cost = takeover_cost(action, expected_mentor) if step in (1, 4) else 0.0
        assert info["intervention_cost"] == pytest.approx(cost)
        assert "physics_action" not in info  # HACO: no physics
        # The pendulum moved by the executed torque (PendulumEnv's own dynamics, one step of dt = 0.05).
        u = float(np.clip(executed[0], -2.0, 2.0))
        thd_next = np.clip(thd + (3 * 10.0 / 2 * np.sin(th) + 3.0 * u) * 0.05, -8.0, 8.0)
        assert env.unwrapped.state[1] == pytest.approx(thd_next, abs=1e-5)
    assert env.total_steps == 5


@pytest.mark.parametrize("mode", ["haco", "warmup", "pe_rlhf-mentor", "pe_rlhf-physics", "pe_rlhf-warmup-physics"])
def test_wrapper_decides_as_the_transform_on_pendulum(mode):
    kwargs = {"warmup_steps": 30} if mode == "warmup" else {}
    if mode == "pe_rlhf-warmup-physics":  # the selector judges the warm-up too: physics wins there as well
        kwargs = {"warmup_steps": 30, "warmup_selection": True}

    def pe_rlhf():  # a fresh, identical selector per face
        if not mode.startswith("pe_rlhf"):
            return {}
        return {"physics": _pendulum_physics, "selector": _selector(3, 1, -1e9 if mode.endswith("mentor") else 1e9)}

    actions, resets = _pendulum_actions(450), [{"seed": s} for s in range(10)]  # 200-step episodes: 2 resets
    transform = TransformedEnv(GymEnv("Pendulum-v1"), InterventionTransform(LargeTorqueMentor(), **pe_rlhf(),
                                                                            **kwargs))
    expected = _torchrl_records(transform, actions, resets)
    records = _gym_records(InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor(), **pe_rlhf(), **kwargs),
                           actions, resets)
    _assert_same(records, expected)
    taken, start = _flags(expected, "intervention"), _flags(expected, "intervention_start")
    assert taken.any() and (~taken).any() and start.sum() >= 5
    if mode == "warmup":
        assert taken[:30].all()
    if mode in ("pe_rlhf-physics", "pe_rlhf-warmup-physics"):
        assert not _flags(expected, "mentor_selected").any()
    if mode == "pe_rlhf-warmup-physics":  # physics proposed and executed at every warm-up step
        assert taken[:30].all() and all(np.abs(r["physics_action"]).sum() > 0
                                        for r in expected[:30] if r["intervention"][0])


def test_the_info_reader_gives_a_torchrl_env_the_transform_keys():
    """GymWrapper over the wrapper + ``InfoToTakeoverKeys`` = GymEnv + ``InterventionTransform``: specs,
    reset defaults and every step's values."""
    adapted = GymWrapper(InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor()))
    adapted.set_info_dict_reader(InfoToTakeoverKeys(adapted.action_spec.shape))
    transform = TransformedEnv(GymEnv("Pendulum-v1"), InterventionTransform(LargeTorqueMentor()))
    check_env_specs(adapted)
    for key in OUT_KEYS:
        assert adapted.full_observation_spec[key] == transform.full_observation_spec[key], key
    reset = adapted.reset(seed=0)
    assert all(key in reset.keys() and not reset[key].any() for key in OUT_KEYS)

    actions, resets = _pendulum_actions(250), [{"seed": s} for s in range(5)]
    records, expected = _torchrl_records(adapted, actions, resets), _torchrl_records(transform, actions, resets)
    _assert_same(records, expected)  # also the root action: the agent's proposal under both
    assert _flags(records, "intervention").any()


def test_non_finite_proposals_are_executed_as_zero_with_a_warning():
    env = InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor())
    env.reset(seed=0)
    with pytest.warns(RuntimeWarning, match="InterventionWrapper: the agent proposed"):
        _, _, _, _, info = env.step(np.array([np.nan], np.float32))
    assert not info["is_intervention"] and info["teleop_action"].tolist() == [0.0]
    assert np.isnan(info["agent_action"]).all()  # reported as proposed


def test_wrapper_errors_name_the_wrapper():
    with pytest.raises(ValueError, match="InterventionWrapper needs both selector and physics"):
        InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor(), physics=_pendulum_physics)
    env = InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor())
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1, np.float32))


# -- the driving env: gymnasium registration, check_env, the professional mentor ---------------------------
def _check_env_quietly(env):
    """``check_env``; the only warning allowed is that ``env`` is wrapped (it is, on purpose)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_close_check=True)
    messages = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert all("different from the unwrapped" in m or "symmetric and normalized" in m for m in messages), messages


def test_gymnasium_make_driving_env_passes_check_env():
    register()  # idempotent: importing pe_rlhf.envs registered it already
    assert ENV_ID in gym.registry
    env = gym.make(ENV_ID, config=FAST_CONFIG)
    assert env.unwrapped.world.horizon == FAST_CONFIG["horizon"]
    check_env(env.unwrapped)
    _check_env_quietly(InterventionWrapper(env, DriverMentor()))  # a deterministic mentor: steps repeat
    env.close()
    other = gym.make(f"pe_rlhf.envs:{ENV_ID}", config=FAST_CONFIG)  # the form that imports the module itself
    assert type(other.unwrapped) is type(env.unwrapped)
    _check_env_quietly(InterventionWrapper(gym.make("Pendulum-v1"), LargeTorqueMentor()))


def _driving_resets(gym_face: bool):
    return [{"options": {"scene_seed": s}} if gym_face else {"scene_seed": s} for s in TRAIN_SEEDS[:20]]


@pytest.mark.parametrize("mode", ["haco", "pe_rlhf"])
def test_wrapper_decides_as_the_transform_on_driving(mode):
    """200 steps (100 in PE-RLHF) of the same agent actions and scenes: the same takeovers, executed actions,
    costs and observations from the transform, the wrapper, and GymWrapper over the wrapper."""
    steps = 200 if mode == "haco" else 100

    def faces():  # a fresh mentor (same seed), physics and selector (same weights) per face
        mentor = make_mentor("professional", seed=3)
        if mode == "haco":
            return {"mentor": mentor}
        return {"mentor": mentor, "physics": IDMMobilPolicy(), "selector": _selector(250, 2, 0.0)}

    actions = _driving_actions(steps)
    transform = make_env(FAST_CONFIG)
    transform.append_transform(InterventionTransform(**faces()))
    expected = _torchrl_records(transform, actions, _driving_resets(False))
    wrapper = InterventionWrapper(make_gym_env(FAST_CONFIG), **faces())
    _assert_same(_gym_records(wrapper, actions, _driving_resets(True)), expected)
    adapted = GymWrapper(InterventionWrapper(make_gym_env(FAST_CONFIG), **faces()))
    adapted.set_info_dict_reader(InfoToTakeoverKeys((2,)))
    _assert_same(_torchrl_records(adapted, actions, _driving_resets(True)), expected)

    taken, start = _flags(expected, "intervention"), _flags(expected, "intervention_start")
    assert taken.any() and (~taken).any() and start.sum() >= 3, (taken.sum(), start.sum())
    if mode == "pe_rlhf":
        physics = np.stack([r["physics_action"] for r in expected])
        assert (np.abs(physics[taken]).sum(-1) > 0).all() and not physics[~taken].any()
