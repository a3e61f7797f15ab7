"""Property-based tests (hypothesis) of the takeover cost, the hybrid selector and the intervention
transform over random actions (zero vectors, the ±1 bounds, NaN, ±inf) and random takeover flags."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import step_mdp

from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.modules import QEnsemble
from pe_rlhf.transforms import HybridActionSelector, InterventionTransform
from pe_rlhf.transforms.intervention import takeover_cost

pytestmark = pytest.mark.usefixtures("one_thread")
SETTINGS = settings(max_examples=60, deadline=None, derandomize=True, database=None)

EDGE = st.sampled_from([0.0, -0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 1e-9])
COMPONENT = st.one_of(EDGE, st.floats(-1.0, 1.0, width=32))
FINITE = st.one_of(st.sampled_from([0.0, 1.0, -1.0]), st.floats(-1.0, 1.0, width=32))
ACTION = st.tuples(COMPONENT, COMPONENT).map(lambda a: np.array(a, dtype=np.float32))
FINITE_ACTION = st.tuples(FINITE, FINITE).map(lambda a: np.array(a, dtype=np.float32))


def same(a, b) -> bool:
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


# --------------------------------------------------------------------------- takeover cost


@SETTINGS
@given(ACTION, ACTION)
def test_takeover_cost_is_always_in_0_2(a, b):
    cost = takeover_cost(a, b)
    assert math.isfinite(cost) and 0.0 <= cost <= 2.0
    assert cost == takeover_cost(b, a)
    usable = lambda x: np.isfinite(x).all() and np.linalg.norm(x) >= 1e-6  # noqa: E731
    if not (usable(a) and usable(b)):
        assert cost == 1.0  # no direction to compare
    elif same(a, b):
        assert cost == pytest.approx(0.0, abs=1e-6)


# --------------------------------------------------------------------------- selector


@SETTINGS
@given(st.integers(1, 6), st.data(), st.sampled_from([-1e9, 0.0, 1e9]), st.booleans())
def test_selector_executes_one_of_the_two_and_never_a_non_finite_one_over_a_finite_one(n, data, epsilon, nan_obs):
    torch.manual_seed(0)
    selector = HybridActionSelector(QEnsemble(3, num_members=2, hidden=(8,)), epsilon_select=epsilon)
    mentor = torch.as_tensor(np.stack([data.draw(ACTION) for _ in range(n)]))
    physics = torch.as_tensor(np.stack([data.draw(ACTION) for _ in range(n)]))
    obs = torch.randn(n, 3)
    if nan_obs:
        obs[0, 0] = math.nan
    hybrid, chosen = selector.select(obs, mentor, physics)
    assert hybrid.shape == (n, 2) and chosen.shape == (n, 1) and chosen.dtype == torch.bool
    for i in range(n):
        picked = mentor[i] if chosen[i] else physics[i]
        assert same(hybrid[i], picked)
        fm, fp = bool(torch.isfinite(mentor[i]).all()), bool(torch.isfinite(physics[i]).all())
        if fm != fp:
            assert bool(chosen[i]) == fm  # the finite one, whatever the ensemble says
        elif fm and not (nan_obs and i == 0) and epsilon != 0.0:
            assert bool(chosen[i]) == (epsilon < 0)  # far thresholds: always / never the mentor
    td = selector(TensorDict({"observation": obs, "mentor_action": mentor, "physics_action": physics}, [n]))
    assert same(td["hybrid_action"], hybrid) and torch.equal(td["mentor_selected"], chosen)


# --------------------------------------------------------------------------- intervention transform


class ToyEnv(EnvBase):
    """Observation = the action the env received (2) + the step count; never done."""

    def __init__(self):
        super().__init__(batch_size=torch.Size([]))
        self.observation_spec = Composite(observation=Unbounded((3,)), shape=[])
        self.action_spec = Bounded(-1.0, 1.0, (2,))
        self.reward_spec = Unbounded((1,))
        self.t = 0

    def _reset(self, tensordict=None, **kwargs):
        self.t = 0
        return TensorDict({"observation": torch.zeros(3), "done": torch.zeros(1, dtype=torch.bool),
                           "terminated": torch.zeros(1, dtype=torch.bool)}, [])

    def _step(self, tensordict):
        self.t += 1
        received = tensordict["action"].float()
        return TensorDict({"observation": torch.cat([received, torch.tensor([float(self.t)])]),
                           "reward": torch.zeros(1), "done": torch.zeros(1, dtype=torch.bool),
                           "terminated": torch.zeros(1, dtype=torch.bool)}, [])

    def _set_seed(self, seed):
        return seed


class ScriptedMentor(Mentor):
    """Takes over on the scripted flags with the scripted actions."""

    def __init__(self, flags, actions):
        self.flags, self.actions, self.i = list(flags), list(actions), 0

    def act(self, env):
        return self.actions[self.i]

    def decide(self, env, agent_action):
        assert np.isfinite(agent_action).all()  # a non-finite proposal never reaches the mentor
        d = MentorDecision(self.flags[self.i], self.actions[self.i])
        self.i += 1
        return d


@SETTINGS
@given(st.data(), st.integers(1, 10), st.integers(0, 3), st.booleans(), st.sampled_from([-1e9, 1e9]))
def test_intervention_transform_invariants(data, steps, warmup, pe_rlhf, epsilon):
    agent = [data.draw(ACTION) for _ in range(steps)]
    flags = [data.draw(st.booleans()) for _ in range(steps)]
    mentor_actions = [data.draw(FINITE_ACTION) for _ in range(steps)]
    physics_actions = iter([data.draw(FINITE_ACTION) for _ in range(steps)])
    selector = physics = None
    if pe_rlhf:
        torch.manual_seed(0)
        selector = HybridActionSelector(QEnsemble(3, num_members=2, hidden=(8,)), epsilon_select=epsilon)
        physics = lambda env: next(physics_actions)  # noqa: E731
    env = TransformedEnv(ToyEnv(), InterventionTransform(ScriptedMentor(flags, mentor_actions), selector, physics,
                                                         warmup_steps=warmup))
    td = env.reset()
    previous = False
    for i in range(steps):
        td["action"] = torch.as_tensor(agent[i])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the non-finite proposal's warning
            td = env.step(td)
        nxt = td["next"]
        executed = nxt["behavior_action"].numpy()
        takeover, start = bool(nxt["intervention"]), bool(nxt["intervention_start"])
        selected, cost = bool(nxt["mentor_selected"]), float(nxt["intervention_cost"])
        assert np.isfinite(executed).all() and same(nxt["observation"][:2], executed)  # the env got it
        assert same(td["action"], agent[i])  # the root keeps the agent's proposal as it was
        assert takeover == (i < warmup or flags[i]) and start == (takeover and not previous)
        assert 0.0 <= cost <= 2.0 and (start or cost == 0.0)
        assert not selected or takeover
        if not takeover:
            assert same(executed, np.where(np.isfinite(agent[i]), agent[i], 0.0))
            assert not nxt["physics_action"].any()
        elif selected or not pe_rlhf or i < warmup:
            assert same(executed, mentor_actions[i])
        else:
            assert same(executed, nxt["physics_action"]) and epsilon > 0
        previous = takeover
        td = step_mdp(td)
