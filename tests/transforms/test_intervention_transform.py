"""InterventionTransform on the real driving env, with a real driver as the mentor (no mocks).

The mentor is ``DriverMentor`` (``tests/_factories.py``): a ``PrivilegedDriver`` that takes over when
the agent's action differs from its own by more than 0.5 in any dimension. Agents are scripted: a
second ``PrivilegedDriver`` (it computes exactly the mentor's action, being called on the same states),
a fixed bad action, or a mix of both.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _factories import FAST_CONFIG, DriverMentor, make_intervention_env
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, ParallelEnv, TransformedEnv
from torchrl.envs.utils import RandomPolicy, check_env_specs

from pe_rlhf.envs import TRAIN_SEEDS
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.mentors import Mentor, MentorDecision, PrivilegedDriver
from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.transforms import HybridActionSelector, InterventionTransform, takeover_cost
from pe_rlhf.transforms.intervention import OUT_KEYS

SCENE = TRAIN_SEEDS[0]
BAD = torch.tensor([-1.0, 0.0])  # full left steering, no throttle
ACTION_KEYS = ("behavior_action", "mentor_action", "physics_action")
FLAG_KEYS = ("intervention", "intervention_start", "mentor_selected")


def _env(mentor=None, config=None, **kwargs):
    env = make_env({**FAST_CONFIG, **(config or {})})
    env.append_transform(InterventionTransform(mentor or DriverMentor(), **kwargs))
    env.set_seed(0)  # scenes drawn at automatic resets come from the env's RNG: fix them
    return env


def _rollout(env, policy, steps, scene=SCENE, **kwargs):
    td = env.reset(TensorDict({"scene_seed": torch.tensor([scene])}, []))
    return env.rollout(steps, policy, tensordict=td, auto_reset=False, **kwargs)


def _driver_agent(env):
    """The agent proposes exactly the mentor's action (its own ``PrivilegedDriver`` on the same states)."""
    driver = PrivilegedDriver()

    def policy(td):
        return td.set("action", torch.as_tensor(driver(unwrap(env))))

    return policy


def _fixed_agent(action, env=None, positions=None):
    def policy(td):
        if positions is not None:
            positions.append(unwrap(env).vehicle.position.copy())
        return td.set("action", action.clone())

    return policy


def _alternating_agent(env, period=4):
    """Drives like the mentor for ``period`` steps, then proposes a bad action for ``period`` steps, ..."""
    driver, step = PrivilegedDriver(), [0]

    def policy(td):
        good = torch.as_tensor(driver(unwrap(env)))  # called every step: stays in sync with the mentor
        bad = (step[0] // period) % 2 == 1
        step[0] += 1
        return td.set("action", torch.tensor([0.9, -0.9]) if bad else good)

    return policy


def _flags(td, key):
    return td["next", key].squeeze(-1)


def _expected_starts(td):
    """Rising edges of ``intervention``; the step after a ``done`` starts from 'no takeover'."""
    taken, done = _flags(td, "intervention"), _flags(td, "done")
    before = torch.zeros_like(taken)
    before[1:] = taken[:-1] & ~done[:-1]
    return taken & ~before


def _cosine_cost(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return 1.0 - a @ b / (np.linalg.norm(a) * np.linalg.norm(b))


# -- the cost function -------------------------------------------------------------------------------
def test_takeover_cost_values_and_zero_norm_guard():
    x = np.array([0.3, -0.4], np.float32)
    assert takeover_cost(x, x) == pytest.approx(0.0, abs=1e-7)
    assert takeover_cost(x, -x) == pytest.approx(2.0)
    assert takeover_cost(x, np.array([0.4, 0.3], np.float32)) == pytest.approx(1.0)  # orthogonal
    # Zero-norm guard: with no direction to compare, the cost is exactly 1 (never NaN).
    for a, b in ((np.zeros(2), x), (x, np.zeros(2)), (np.zeros(2), np.zeros(2)), (np.full(2, 1e-9), x)):
        assert takeover_cost(a, b) == 1.0


# -- HACO mode -----------------------------------------------------------------------------------------
def test_no_takeover_when_the_agent_drives_like_the_mentor():
    env = _env()
    td = _rollout(env, _driver_agent(env), 40)
    assert td.batch_size[0] == 40
    assert not _flags(td, "intervention").any() and not _flags(td, "intervention_start").any()
    assert not _flags(td, "mentor_selected").any()
    assert torch.equal(td["next", "behavior_action"], td["action"])
    assert torch.equal(td["next", "mentor_action"], td["action"])
    assert (td["next", "intervention_cost"] == 0).all()
    assert (td["next", "physics_action"] == 0).all()


def test_takeover_executes_the_mentor_action_and_keeps_the_agent_proposal():
    env, positions = _env(), []
    td = _rollout(env, _fixed_agent(BAD, env, positions), 30)
    assert _flags(td, "intervention").all() and _flags(td, "mentor_selected").all()
    assert torch.equal(td["next", "behavior_action"], td["next", "mentor_action"])
    assert (td["action"] == BAD).all()  # the rollout's root action is the agent's proposal
    assert ((td["next", "behavior_action"] - BAD).abs().amax(-1) > 0.5).all()

    def replay(actions, pos):
        other = make_env(FAST_CONFIG)
        it = iter(actions)

        def policy(tensordict):
            pos.append(unwrap(other).vehicle.position.copy())
            return tensordict.set("action", next(it).clone())

        return _rollout(other, policy, len(actions))

    # The simulator moved by the executed action: a second env driven directly with the behaviour
    # actions follows the identical ego trajectory; driven with the agent's actions it does not.
    replayed = []
    td2 = replay(td["next", "behavior_action"], replayed)
    np.testing.assert_array_equal(np.array(positions), np.array(replayed))
    assert torch.equal(td["next", "observation"], td2["next", "observation"])
    naive = []
    replay(td["action"], naive)  # (full left steering leaves the road early: compare the common part)
    assert np.abs(np.array(naive) - np.array(positions[:len(naive)])).max() > 1.0


def test_cost_is_charged_only_at_takeover_starts():
    env = _env()
    td = _rollout(env, _alternating_agent(env), 40)
    taken, start = _flags(td, "intervention"), _flags(td, "intervention_start")
    assert taken.any() and (~taken).any()
    assert torch.equal(start, _expected_starts(td))
    assert start.sum() >= 3  # several separate takeovers
    cost = td["next", "intervention_cost"].squeeze(-1)
    assert (cost[~start] == 0).all()
    for t in start.nonzero().flatten().tolist():
        expected = _cosine_cost(td["action"][t], td["next", "behavior_action"][t])
        assert cost[t].item() == pytest.approx(expected, rel=1e-5, abs=1e-6) and cost[t] > 0
    # Outside takeovers the agent's action is executed.
    assert torch.equal(td["next", "behavior_action"][~taken], td["action"][~taken])


def test_zero_agent_action_costs_exactly_one():
    env = _env(DriverMentor(tolerance=0.0))  # any difference is a takeover
    td = _rollout(env, _fixed_agent(torch.zeros(2)), 10)
    assert _flags(td, "intervention").all()
    assert _flags(td, "intervention_start").tolist() == [True] + [False] * 9
    cost = td["next", "intervention_cost"].squeeze(-1)
    assert cost[0].item() == 1.0 and (cost[1:] == 0).all()
    assert not torch.isnan(cost).any()


def test_warmup_mentor_drives_every_step_then_normal():
    env = _env(warmup_steps=20)
    td = _rollout(env, _driver_agent(env), 30)
    taken = _flags(td, "intervention")
    assert taken[:20].all() and not taken[20:].any()  # a good agent: takeovers only during warm-up
    assert _flags(td, "intervention_start").tolist() == [True] + [False] * 29
    assert _flags(td, "mentor_selected")[:20].all()
    assert torch.equal(td["next", "behavior_action"][:20], td["next", "mentor_action"][:20])
    assert env.transform[-1].total_steps == 30

    # A mentor that never takes over still drives during warm-up; afterwards the agent's action runs.
    env = _env(DriverMentor(tolerance=math.inf), warmup_steps=20)
    proposal = torch.tensor([0.0, 0.3])
    td = _rollout(env, _fixed_agent(proposal), 30)
    assert _flags(td, "intervention")[:20].all() and not _flags(td, "intervention")[20:].any()
    assert torch.equal(td["next", "behavior_action"][:20], td["next", "mentor_action"][:20])
    assert not torch.equal(td["next", "behavior_action"][:20], td["action"][:20])
    assert (td["next", "behavior_action"][20:] == proposal).all()


class _SteerOffMentor(Mentor):
    """A hostile mentor: in control it steers hard left at full throttle, off the road within seconds."""

    name = "steer-off"

    def act(self, env) -> np.ndarray:
        return np.array([-1.0, 1.0], dtype=np.float32)

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        return MentorDecision(False, self.act(env))


@pytest.mark.parametrize("warmup_selection", [False, True])
def test_warmup_selection_lets_the_forecast_overrule_a_hostile_warmup(warmup_selection):
    """The paper's warm-up bypasses the selector: a hostile mentor drives off the road. With
    ``warmup_selection`` the physics forecast judges each warm-up step, executes physics where the
    mentor's action fails sooner, and the car stays on the road."""
    from pe_rlhf.physics.safety import SafetyForecastValue

    selector = HybridActionSelector(SafetyForecastValue(), epsilon_select=-0.5)
    env = _env(_SteerOffMentor(), selector=selector, physics=IDMMobilPolicy(), warmup_steps=60,
               warmup_selection=warmup_selection)
    td = _rollout(env, _fixed_agent(torch.tensor([0.0, 0.3])), 60, break_when_any_done=True)
    assert _flags(td, "intervention").all()
    off_road = bool(_flags(td, "out_of_road").any())
    physics_ran = ~_flags(td, "mentor_selected")
    if warmup_selection:
        assert not off_road and td.shape[0] == 60
        assert physics_ran.any() and (td["next", "physics_action"].abs().sum(-1) > 0).all()
        np.testing.assert_array_equal(td["next", "behavior_action"][physics_ran].numpy(),
                                      td["next", "physics_action"][physics_ran].numpy())
    else:
        assert off_road and not physics_ran.any() and (td["next", "physics_action"] == 0).all()


def test_warmup_selection_needs_a_selector_and_the_mentor_driving():
    with pytest.raises(ValueError, match="warmup_selection needs a selector"):
        _env(warmup_steps=5, warmup_selection=True)


class _RecordingDriver:
    """A warm-up driver: brakes gently straight ahead, and records the observations it was given."""

    def __init__(self):
        self.observations, self.resets = [], 0

    def reset(self):
        self.resets += 1

    def __call__(self, obs, env):
        assert env is unwrap(env)  # the simulator itself, as the mentor gets it
        self.observations.append(np.asarray(obs).copy())
        return np.array([0.0, -0.2], dtype=np.float32)


def test_warmup_driver_drives_the_warmup_instead_of_the_mentor():
    driver = _RecordingDriver()
    env = _env(warmup_steps=20, warmup_driver=driver)
    proposal = torch.tensor([0.0, 0.3])
    td = _rollout(env, _fixed_agent(proposal), 30)
    expert = torch.tensor([0.0, -0.2])
    assert (td["next", "behavior_action"][:20] == expert).all()  # the expert drove, not the mentor
    assert not torch.equal(td["next", "behavior_action"][:20], td["next", "mentor_action"][:20])
    assert _flags(td, "intervention")[:20].all()  # forced control, as in the mentor's warm-up
    assert not _flags(td, "mentor_selected")[:20].any()  # ... but the mentor's action never ran
    assert len(driver.observations) == 20 and driver.resets == 1  # not asked after the warm-up
    np.testing.assert_array_equal(np.stack(driver.observations), td["observation"][:20].numpy())
    after = td["next", "behavior_action"][20:]
    assert (after == proposal).logical_or(_flags(td, "intervention")[20:, None]).all()


def test_warmup_driver_bad_output_is_an_error_naming_it():
    env = _env(warmup_steps=5, warmup_driver=lambda obs, env: np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="warmup_driver returned"):
        _rollout(env, _fixed_agent(torch.tensor([0.0, 0.3])), 3)
    with pytest.raises(TypeError, match="warmup_driver"):
        InterventionTransform(DriverMentor(), warmup_steps=5, warmup_driver="sac")


def test_episode_end_does_not_leak_takeover_state():
    mentor = DriverMentor()
    env = _env(mentor, config={"horizon": 10})
    td = _rollout(env, _fixed_agent(BAD), 25, break_when_any_done=False)
    done = _flags(td, "done")
    assert done[9] and done[19] and done.sum() == 2
    assert _flags(td, "intervention").all()  # the takeover is active when each episode ends
    starts = _flags(td, "intervention_start")
    assert starts.nonzero().flatten().tolist() == [0, 10, 20]  # each episode's first step is a start
    assert (td["next", "intervention_cost"].squeeze(-1)[[0, 10, 20]] > 0).all()
    assert mentor.resets == 3


# -- PE-RLHF mode: physics proposal and hybrid selection -------------------------------------------------
@pytest.mark.parametrize("epsilon, mentor_wins", [(-1e9, True), (1e9, False)])
def test_selector_executes_mentor_or_physics_action(epsilon, mentor_wins):
    torch.manual_seed(0)
    selector = HybridActionSelector(QEnsemble(250, 2, num_members=2, hidden=(16,)), epsilon_select=epsilon)
    env = _env(selector=selector, physics=IDMMobilPolicy())
    reference, expected = IDMMobilPolicy(), []

    def bad_agent(td):  # records the physics action at the state the transform is about to decide on
        expected.append(reference(unwrap(env)))
        return td.set("action", BAD.clone())

    td = _rollout(env, bad_agent, 25)
    assert _flags(td, "intervention").all()
    physics = td["next", "physics_action"]
    np.testing.assert_array_equal(physics.numpy(), np.stack(expected).astype(np.float32))
    assert (physics.abs().sum(-1) > 0).any()
    winner = td["next", "mentor_action"] if mentor_wins else physics
    assert torch.equal(td["next", "behavior_action"], winner)
    assert (_flags(td, "mentor_selected") == mentor_wins).all()
    assert (td["action"] == BAD).all()
    # The cost compares the agent's proposal with the executed (hybrid) action.
    assert td["next", "intervention_cost"][0].item() == pytest.approx(_cosine_cost(BAD, winner[0]), abs=1e-6)


def test_physics_action_is_zero_outside_takeovers():
    selector = HybridActionSelector(QEnsemble(250, 2, num_members=2, hidden=(16,)), epsilon_select=1e9)
    env = _env(selector=selector, physics=IDMMobilPolicy())
    td = _rollout(env, _alternating_agent(env), 24)
    taken = _flags(td, "intervention")
    assert taken.any() and (~taken).any()
    physics = td["next", "physics_action"]
    assert (physics[~taken] == 0).all() and (physics[taken].abs().sum(-1) > 0).all()
    assert torch.equal(td["next", "behavior_action"][taken], physics[taken])
    assert torch.equal(td["next", "behavior_action"][~taken], td["action"][~taken])
    assert not _flags(td, "mentor_selected").any()


def test_the_selector_hears_the_previous_choice_within_a_takeover_only():
    """At a takeover's first step the selector gets ``previous=None``; later steps get the choice just made."""

    class RecordingSelector(HybridActionSelector):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.previous = []

        def select(self, observation, mentor_action, physics_action, previous=None):
            self.previous.append(previous)
            return super().select(observation, mentor_action, physics_action, previous)

    torch.manual_seed(0)
    selector = RecordingSelector(QEnsemble(250, 2, num_members=2, hidden=(16,)), epsilon_select=0.0,
                                 switch_margin=float("inf"))
    env = _env(selector=selector, physics=IDMMobilPolicy())
    td = _rollout(env, _alternating_agent(env), 40)
    taken, start = _flags(td, "intervention"), _flags(td, "intervention_start")
    chosen = _flags(td, "mentor_selected")
    assert start.sum() >= 2 and len(selector.previous) == int(taken.sum())
    steps = taken.nonzero().squeeze(-1).tolist()
    for heard, t in zip(selector.previous, steps):
        if start[t]:
            assert heard is None
        else:
            assert heard == bool(chosen[t - 1]) and bool(chosen[t]) == heard  # inf margin: committed


def test_selector_and_physics_come_together():
    selector = HybridActionSelector(QEnsemble(250, 2, num_members=2, hidden=(8,)))
    with pytest.raises(ValueError, match="both selector and physics"):
        InterventionTransform(DriverMentor(), selector=selector)
    # physics without a selector proposes to a HybridSelectionTransform
    # (tests/transforms/test_hybrid_selection_transform.py)
    assert InterventionTransform(DriverMentor(), physics=IDMMobilPolicy()).core.propose_physics
    with pytest.raises(ValueError, match="warmup_steps"):
        InterventionTransform(DriverMentor(), warmup_steps=-1)


# -- specs, keys, batched and collected use --------------------------------------------------------------
@pytest.mark.parametrize("pe_rlhf", [False, True])
def test_specs_and_keys_at_reset_and_every_step(pe_rlhf):
    kwargs = {}
    if pe_rlhf:
        kwargs = {"selector": HybridActionSelector(QEnsemble(250, 2, num_members=2, hidden=(8,))),
                  "physics": IDMMobilPolicy()}
    env = _env(**kwargs)
    check_env_specs(env)
    spec = env.full_observation_spec
    for key in ACTION_KEYS:
        assert spec[key].shape == (2,) and spec[key].dtype == torch.float32
    for key in FLAG_KEYS:
        assert spec[key].shape == (1,) and spec[key].dtype == torch.bool
    assert spec["intervention_cost"].shape == (1,) and spec["intervention_cost"].dtype == torch.float32

    reset = env.reset(TensorDict({"scene_seed": torch.tensor([SCENE])}, []))
    for key in OUT_KEYS:  # defaults at reset: zeros / False
        assert key in reset.keys() and not reset[key].any(), key
        assert reset[key].dtype == spec[key].dtype and reset[key].shape == spec[key].shape
    td = env.rollout(12, _alternating_agent(env, period=3), tensordict=reset, auto_reset=False)
    for key in OUT_KEYS:
        assert td["next", key].shape == (12, *spec[key].shape) and td["next", key].dtype == spec[key].dtype


def test_inside_parallel_env():
    penv = ParallelEnv(2, make_intervention_env)
    try:
        torch.manual_seed(0)
        td = penv.rollout(15, break_when_any_done=False)
        assert td.batch_size == (2, 15)
        for key in ACTION_KEYS:
            assert td["next", key].shape == (2, 15, 2) and td["next", key].dtype == torch.float32
        for key in FLAG_KEYS:
            assert td["next", key].shape == (2, 15, 1) and td["next", key].dtype == torch.bool
        assert td["next", "intervention_cost"].shape == (2, 15, 1)
        taken = td["next", "intervention"].squeeze(-1)
        assert taken.any()  # random proposals differ from the driver's
        assert torch.equal(td["next", "behavior_action"][taken], td["next", "mentor_action"][taken])
        assert torch.equal(td["next", "behavior_action"][~taken], td["action"][~taken])
        for i in range(2):
            assert torch.equal(_flags(td[i], "intervention_start"), _expected_starts(td[i]))
    finally:
        penv.close()


def test_inside_a_collector_across_episodes():
    env = make_intervention_env({"horizon": 15})
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=20, total_frames=60)
    try:
        torch.manual_seed(0)
        batches = [b for b in collector]
    finally:
        collector.shutdown()
    for b in batches:
        assert b.batch_size == (20,)
        for key in OUT_KEYS:
            assert ("next", key) in b.keys(True), key
    td = torch.cat(batches)  # one env: the batches are consecutive
    assert _flags(td, "done").sum() >= 3
    assert torch.equal(_flags(td, "intervention_start"), _expected_starts(td))
    taken = _flags(td, "intervention")
    assert torch.equal(td["next", "behavior_action"][taken], td["next", "mentor_action"][taken])
    assert torch.equal(td["next", "behavior_action"][~taken], td["action"][~taken])


# -- which simulator the mentor sees ----------------------------------------------------------------------
class _RecordingMentor(Mentor):
    """Never takes over; remembers the env object it was handed."""

    def __init__(self):
        self.seen = []

    def act(self, env):
        self.seen.append(env)
        return np.zeros(1, np.float32)

    def decide(self, env, agent_action):
        return MentorDecision(False, self.act(env))


def test_mentor_sees_the_driving_env_or_the_gym_env_unwrapped():
    env = _env()
    assert env.transform[-1].driving_env is unwrap(env)

    gym_env = GymEnv("Pendulum-v1")
    mentor = _RecordingMentor()
    pendulum = TransformedEnv(gym_env, InterventionTransform(mentor))
    check_env_specs(pendulum)
    td = pendulum.rollout(5)
    assert pendulum.transform.driving_env is gym_env._env.unwrapped
    assert mentor.seen and all(e is gym_env._env.unwrapped for e in mentor.seen)
    assert hasattr(mentor.seen[0], "state")  # PendulumEnv: the true (theta, theta_dot)
    assert td["next", "behavior_action"].shape == (5, 1) and not td["next", "intervention"].any()


def test_every_takeover_key_renamed_in_the_transform_and_the_loss_trains():
    """All seven outputs renamed (``out_keys``), the loss told the new names (``set_keys``): a rollout
    carries only the new names, and PERLHFLoss takes gradient steps on it."""
    from pe_rlhf.modules.networks import make_actor, make_qvalue
    from pe_rlhf.objectives import PERLHFLoss
    from pe_rlhf.transforms.keys import OUT_KEYS

    renamed = [f"tk_{k}" for k in OUT_KEYS]
    torch.manual_seed(0)
    selector = HybridActionSelector(QEnsemble(250, 2, num_members=2, hidden=(16,)), epsilon_select=0.0)
    env = _env(selector=selector, physics=IDMMobilPolicy(), warmup_steps=5, out_keys=renamed)
    td = _rollout(env, _alternating_agent(env), 40)
    nxt = td["next"]
    assert all(k in nxt.keys() for k in renamed) and not any(k in nxt.keys() for k in OUT_KEYS)
    assert nxt["tk_intervention"].any() and (nxt["tk_behavior_action"] != td["action"]).any()

    actor, q, q_int = make_actor(250, hidden=(32,)), make_qvalue(250, hidden=(32,)), make_qvalue(250, hidden=(32,))
    loss = PERLHFLoss(actor, q, q_int, action_dim=2)
    loss.set_keys(behavior_action=("next", "tk_behavior_action"), intervention=("next", "tk_intervention"),
                  intervention_start=("next", "tk_intervention_start"),
                  intervention_cost=("next", "tk_intervention_cost"))
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in loss.qvalue_network_params.flatten_keys().values()]
    for _ in range(3):
        out = loss(td)
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        assert torch.isfinite(total)
        optim.zero_grad()
        total.backward()
        optim.step()
    after = list(loss.qvalue_network_params.flatten_keys().values())
    assert any(not torch.equal(a, b) for a, b in zip(before, after))
    assert out["intervention_rate"] == nxt["tk_intervention"].float().mean()


def test_out_keys_must_be_seven_distinct_names():
    with pytest.raises(ValueError, match="out_keys are 7 distinct names"):
        InterventionTransform(DriverMentor(), out_keys=["a"] * 7)
