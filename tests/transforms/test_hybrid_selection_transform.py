"""HybridSelectionTransform: the hybrid action selection as a TorchRL transform of its own.

Two sources feed it: our ``InterventionTransform`` given physics and no selector (on the real driving env, with
a real driver as the mentor), and a transform playing another library's intervention info on Pendulum. The
selection sits before its source in the ``Compose`` (TorchRL runs inverse transforms last to first).
"""

from __future__ import annotations

import pytest
import torch
from _factories import FAST_CONFIG, DriverMentor
from tensordict import TensorDict
from torchrl.envs import Compose, GymEnv, SerialEnv, Transform, TransformedEnv
from torchrl.envs.utils import check_env_specs

from pe_rlhf.envs import TRAIN_SEEDS
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.mentors import PrivilegedDriver
from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.transforms import HybridActionSelector, HybridSelectionTransform, InterventionTransform
from pe_rlhf.transforms.keys import OUT_KEYS


def _alternating_agent(env, period=4):
    """Drives like the mentor for ``period`` steps, then proposes a bad action for ``period`` steps, ..."""
    driver, step = PrivilegedDriver(), [0]

    def policy(td):
        good = torch.as_tensor(driver(unwrap(env)))
        bad = (step[0] // period) % 2 == 1
        step[0] += 1
        return td.set("action", torch.tensor([0.9, -0.9]) if bad else good)

    return policy


def _driving_rollout(transform, steps=48):
    env = make_env(FAST_CONFIG)
    env.append_transform(transform)
    env.set_seed(0)
    td = env.reset(TensorDict({"scene_seed": torch.tensor([TRAIN_SEEDS[0]])}, []))
    return env.rollout(steps, _alternating_agent(env), tensordict=td, auto_reset=False)


@pytest.mark.parametrize("switch_margin, warmup_steps, patience, imminent", [
    (None, 6, 1, None), (float("inf"), 0, 1, None), (0.05, 0, 1, None), (None, 0, 3, None), (None, 6, 2, 0.0)])
def test_selection_transform_after_our_proposals_decides_as_the_built_in_selector(switch_margin, warmup_steps,
                                                                                  patience, imminent):
    """``Compose(HybridSelectionTransform(s), InterventionTransform(mentor, physics=p))`` writes the same seven
    takeover keys, step by step, as ``InterventionTransform(mentor, s, p)``: the same executed actions, choices
    and costs (warm-up bypassed, the sticky choice held within a takeover, a patient veto counted per takeover)."""
    torch.manual_seed(0)
    ensemble = QEnsemble(250, 2, num_members=2, hidden=(16,))

    def selector(veto_patience=patience):
        return HybridActionSelector(ensemble, epsilon_select=0.0, switch_margin=switch_margin,
                                    veto_patience=veto_patience, imminent_failure=imminent)

    built_in = _driving_rollout(InterventionTransform(DriverMentor(), selector(), IDMMobilPolicy(),
                                                     warmup_steps=warmup_steps))
    composed = _driving_rollout(Compose(
        HybridSelectionTransform(selector()),
        InterventionTransform(DriverMentor(), physics=IDMMobilPolicy(), warmup_steps=warmup_steps)))
    for key in OUT_KEYS:
        torch.testing.assert_close(composed["next", key], built_in["next", key], rtol=0, atol=0, msg=key)
    taken = built_in["next", "intervention"].squeeze(-1)
    chosen = built_in["next", "mentor_selected"].squeeze(-1)
    judged = taken.clone()
    judged[:warmup_steps] = False
    assert judged.any() and (chosen[judged].any() or switch_margin is not None)
    if switch_margin is None:  # a random ensemble at eps 0: both choices happen
        assert chosen[judged].any() and (~chosen[judged]).any()
    physics = built_in["next", "physics_action"][judged]
    assert (physics.abs().sum(-1) > 0).all()
    if patience > 1 and imminent is None:  # the count changed choices: judging every step alone chooses otherwise
        alone = _driving_rollout(InterventionTransform(DriverMentor(), selector(1), IDMMobilPolicy(),
                                                       warmup_steps=warmup_steps))
        assert not torch.equal(alone["next", "mentor_selected"], built_in["next", "mentor_selected"])


@pytest.mark.parametrize("selection_after", [False, True])
def test_proposals_without_a_selection_nearer_the_simulator_fail_at_the_first_judged_step(selection_after):
    """No selection at all, or one appended after the source (its inverse runs first and would judge the last
    step's proposals, which the root carries as observations): a one-line error, not a silent mentor."""
    env = make_env(FAST_CONFIG)
    env.append_transform(InterventionTransform(DriverMentor(), physics=IDMMobilPolicy()))
    if selection_after:
        env.append_transform(HybridSelectionTransform(HybridActionSelector(QEnsemble(250, 2, num_members=2,
                                                                                     hidden=(8,)))))
    td = env.reset(TensorDict({"scene_seed": torch.tensor([TRAIN_SEEDS[0]])}, []))
    with pytest.raises(RuntimeError, match="none judged this step: put one before it"):
        env.rollout(20, lambda td: td.set("action", torch.tensor([0.9, -0.9])), tensordict=td, auto_reset=False)


# -- another library's intervention info, on Pendulum ------------------------------------------------------
class TeleopInfo(Transform):
    """Plays an outside source: on the way to the simulator it writes a teleoperator's action (+1), a
    controller's (-1) and a takeover flag on every other step, under the given names."""

    def __init__(self, keys=("mentor_action", "physics_action", "intervention")):
        super().__init__()
        self.keys, self.step_count = keys, 0

    def _reset(self, tensordict, tensordict_reset):
        self.step_count = 0
        return tensordict_reset

    def _inv_call(self, tensordict):
        shape = tensordict.get("action").shape
        tensordict.set(self.keys[0], torch.ones(shape))
        tensordict.set(self.keys[1], -torch.ones(shape))
        tensordict.set(self.keys[2], torch.full((*shape[:-1], 1), self.step_count % 2 == 0))
        self.step_count += 1
        return tensordict


class SignValue(torch.nn.Module):
    """A value source: an action is worth ``a * sin(theta)`` (the observation's second entry), one head."""

    def values(self, observation, actions):
        return (actions[..., 0] * observation[..., 1]).unsqueeze(0)


def _pendulum(selection, source, batched=False):
    base = SerialEnv(2, lambda: GymEnv("Pendulum-v1")) if batched else GymEnv("Pendulum-v1")
    env = TransformedEnv(base, Compose(selection, source))
    env.set_seed(0)
    return env


@pytest.mark.parametrize("batched", [False, True])
def test_selection_after_an_outside_source_executes_the_better_proposal(batched):
    selection = HybridSelectionTransform(HybridActionSelector(SignValue(), epsilon_select=0.0))
    env = _pendulum(selection, TeleopInfo(), batched)
    check_env_specs(env)
    td = env.rollout(12, lambda td: td.set("action", torch.zeros(td.get("observation").shape[:-1] + (1,))),
                     break_when_any_done=False)
    executed = td["next", "behavior_action"]
    judged = torch.arange(12) % 2 == 0  # time is the last batch dim: (12,) or (2, 12)
    sin = td["observation"][..., 1:2]
    expected = torch.where(sin >= -sin, torch.ones_like(sin), -torch.ones_like(sin))  # value +sin vs -sin
    expected = torch.where(judged.unsqueeze(-1), expected, torch.zeros_like(sin))
    torch.testing.assert_close(executed, expected)
    assert torch.equal(td["next", "mentor_selected"], judged.unsqueeze(-1) & (sin >= 0))
    assert (td["action"] == 0).all()  # the rollout keeps the agent's proposal at the root
    if not batched:  # the simulator moved by the executed action
        assert float(unwrap(env)._env.unwrapped.last_u) == pytest.approx(float(executed[-1]))


def test_renamed_keys_and_the_wrong_order():
    names = ("tele_action", "ctrl_action", "tele_takeover")
    selection = HybridSelectionTransform(HybridActionSelector(SignValue(), epsilon_select=0.0),
                                         in_keys=("action", "observation", *names),
                                         out_keys=("executed", "tele_chosen"))
    td = _pendulum(selection, TeleopInfo(names)).rollout(6, break_when_any_done=False)
    assert td["next", "executed"].abs().sum() > 0 and "tele_chosen" in td["next"].keys()
    assert "behavior_action" not in td["next"].keys()

    wrong = TransformedEnv(GymEnv("Pendulum-v1"), Compose(
        TeleopInfo(), HybridSelectionTransform(HybridActionSelector(SignValue()))))
    with pytest.raises(KeyError, match="must come after this transform in the Compose"):
        wrong.rollout(3)
    with pytest.raises(ValueError, match="in_keys are"):
        HybridSelectionTransform(HybridActionSelector(SignValue()), in_keys=("action",))
    with pytest.raises(TypeError, match="needs a HybridActionSelector"):
        HybridSelectionTransform(SignValue())


class ScheduleInfo(TeleopInfo):
    """``TeleopInfo`` with the takeover flags of a schedule: ``flags[t]`` (one per batch row) at step ``t``."""

    def __init__(self, flags):
        super().__init__()
        self.flags = torch.as_tensor(flags, dtype=torch.bool)

    def _inv_call(self, tensordict):
        shape = tensordict.get("action").shape
        tensordict.set("mentor_action", torch.ones(shape))
        tensordict.set("physics_action", -torch.ones(shape))
        tensordict.set("intervention", self.flags[self.step_count].reshape(*shape[:-1], 1).clone())
        self.step_count += 1
        return tensordict


class PhysicsBetter(torch.nn.Module):
    """A value source that vetoes the mentor at every step: the mentor's action (+1) is worth 0, physics' 1."""

    def values(self, observation, actions):
        return (actions[..., 0] < 0).float().unsqueeze(0)


def _zero_action(td):
    return td.set("action", torch.zeros(td.get("observation").shape[:-1] + (1,)))


def test_a_patient_veto_is_counted_per_row_as_the_selector_counts_one_takeover():
    """Batched Pendulum, takeovers starting and ending at different steps in each row: every judged step's
    choice is the one a ``HybridActionSelector`` makes when fed that row alone, step by step (``previous=None``
    where the row's takeover starts)."""
    flags = torch.tensor([[1, 0], [1, 1], [1, 1], [1, 0], [0, 1], [1, 1], [1, 1], [1, 1], [1, 0], [1, 1],
                          [1, 1], [0, 1], [1, 1], [1, 1]], dtype=torch.bool)
    selection = HybridSelectionTransform(HybridActionSelector(SignValue(), epsilon_select=0.0, veto_patience=2))
    td = _pendulum(selection, ScheduleInfo(flags), batched=True).rollout(len(flags), _zero_action,
                                                                        break_when_any_done=False)
    chosen = td["next", "mentor_selected"].squeeze(-1)  # (2, T)
    kept_through_a_veto = 0
    for row in range(2):
        reference = HybridActionSelector(SignValue(), epsilon_select=0.0, veto_patience=2)
        previous = None
        for t in range(len(flags)):
            if not flags[t, row]:
                assert not chosen[row, t]
                previous = None
                continue
            _, expected = reference.select(td["observation"][row, t], torch.ones(1), -torch.ones(1), previous)
            assert bool(chosen[row, t]) == bool(expected.item()), (row, t)
            previous = bool(expected.item())
            kept_through_a_veto += int(previous and td["observation"][row, t, 1] < 0)  # vetoed, mentor kept
    assert kept_through_a_veto > 0 and (~chosen[flags.T]).any()  # patience acted, and vetoes replaced the mentor


def test_the_veto_count_restarts_at_a_reset_and_only_in_the_rows_reset():
    """Every step judged, the mentor vetoed at every step, patience 3: the mentor keeps two steps, physics takes
    the third on. A reset mid-takeover starts the count again; a partial reset only in the row reset."""
    selection = HybridSelectionTransform(HybridActionSelector(PhysicsBetter(), epsilon_select=0.0, veto_patience=3))
    env = _pendulum(selection, ScheduleInfo(torch.ones(16, 2)), batched=True)
    first = env.rollout(4, _zero_action, break_when_any_done=False)
    expected = torch.tensor([True, True, False, False])
    assert torch.equal(first["next", "mentor_selected"].squeeze(-1), torch.stack([expected, expected]))
    assert torch.equal(selection.veto_counts(), torch.tensor([4, 4]))
    partial = env.reset(first[..., -1]["next"].clone().set("_reset", torch.tensor([[True], [False]])))
    assert torch.equal(selection.veto_counts(), torch.tensor([0, 4]))
    second = env.rollout(3, _zero_action, tensordict=partial, auto_reset=False, break_when_any_done=False)
    assert torch.equal(second["next", "mentor_selected"].squeeze(-1),
                       torch.tensor([[True, True, False], [False, False, False]]))
    env.reset()  # every row
    assert torch.equal(selection.veto_counts(), torch.tensor([0, 0]))
    third = env.rollout(3, _zero_action, break_when_any_done=False)
    assert torch.equal(third["next", "mentor_selected"].squeeze(-1), torch.tensor([[True, True, False]] * 2))
