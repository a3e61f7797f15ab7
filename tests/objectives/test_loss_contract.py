"""TorchRL's ``LossModule`` contract, checked on every loss written here the way TorchRL's own tests check
``SACLoss`` and ``TD3Loss``: ``repr``, ``in_keys`` (enough to compute the loss, nothing the batch lacks),
``out_keys`` (what ``forward`` returns), keyword calls through ``dispatch`` (TorchRL's ``*_notensordict`` tests),
``select_out_keys``, ``set_keys`` and ``make_value_estimator`` (the supported estimator built, the others
refused with one line naming what is supported).

A new loss joins by adding one ``Case`` to ``LOSSES`` (:mod:`pe_rlhf.objectives.contract` says how to write it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal
from torchrl.objectives import ValueEstimators
from torchrl.objectives.value import GAE, TD0Estimator

from pe_rlhf.modules import QEnsemble, make_actor, make_deterministic_actor, make_qvalue
from pe_rlhf.objectives import (CPOLoss, LagrangeMultiplier, PERLHFLoss, PPOLagLoss, ProxyValueLoss, QEnsembleTDLoss,
                                SACLagLoss)
from pe_rlhf.objectives.contract import UnsupportedValueEstimator
from pe_rlhf.objectives.perlhf import make_transitions

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore:No target network updater")]

OBS, ACT, B, T = 4, 2, 16, 5


def perlhf(**kwargs) -> PERLHFLoss:
    torch.manual_seed(0)
    return PERLHFLoss(make_actor(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)),
                      **kwargs)


def proxy_value() -> ProxyValueLoss:
    torch.manual_seed(0)
    return ProxyValueLoss(make_deterministic_actor(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)), policy_delay=1)


def q_ensemble_td() -> QEnsembleTDLoss:
    torch.manual_seed(0)
    return QEnsembleTDLoss(QEnsemble(OBS, ACT, num_members=3, hidden=(16,)))


def ensemble_batch() -> TensorDict:
    td = perlhf_batch()
    td.set(("next", "action"), torch.rand(B, ACT, generator=torch.Generator().manual_seed(2)) * 2 - 1)
    return td


def perlhf_batch() -> TensorDict:
    g = torch.Generator().manual_seed(1)
    intervention = torch.rand(B, 1, generator=g) < 0.5
    terminated = torch.rand(B, 1, generator=g) < 0.3
    agent = torch.rand(B, ACT, generator=g) * 2 - 1
    behavior = torch.where(intervention, torch.rand(B, ACT, generator=g) * 2 - 1, agent)
    td = make_transitions(torch.randn(B, OBS, generator=g), torch.randn(B, OBS, generator=g), agent, behavior,
                          intervention, intervention, terminated, torch.randn(B, 1, generator=g))
    td.set(("next", "success"), terminated & (torch.rand(B, 1, generator=g) < 0.5))
    return td


def sac_lag() -> SACLagLoss:
    torch.manual_seed(0)
    return SACLagLoss(make_actor(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)),
                      lagrange_multiplier=LagrangeMultiplier(init=0.5))


def sac_batch() -> TensorDict:
    g = torch.Generator().manual_seed(1)
    return TensorDict({"observation": torch.randn(B, OBS, generator=g),
                       "action": torch.rand(B, ACT, generator=g) * 2 - 1,
                       "next": {"observation": torch.randn(B, OBS, generator=g),
                                "reward": torch.randn(B, 1, generator=g), "cost": torch.rand(B, 1, generator=g),
                                "done": torch.zeros(B, 1, dtype=torch.bool),
                                "terminated": torch.zeros(B, 1, dtype=torch.bool)}}, [B])


def gaussian_actor() -> ProbabilisticActor:
    net = nn.Sequential(MLP(in_features=OBS, out_features=2 * ACT, num_cells=[16]), NormalParamExtractor())
    return ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"],
                              distribution_class=TanhNormal, return_log_prob=True)


def value(out_key: str) -> TensorDictModule:
    return TensorDictModule(MLP(in_features=OBS, out_features=1, num_cells=[16]), ["observation"], [out_key])


def ppo_lag() -> PPOLagLoss:
    torch.manual_seed(0)
    return PPOLagLoss(gaussian_actor(), value("state_value"), value("state_cost_value"),
                      lagrange_multiplier=LagrangeMultiplier(init=0.5))


def cpo() -> CPOLoss:
    torch.manual_seed(0)
    return CPOLoss(gaussian_actor(), value("state_value"), value("state_cost_value"))


def trajectory_batch() -> TensorDict:
    """``(B, T)`` steps whose actions and log-probs come from ``gaussian_actor()`` (seed 0)."""
    g = torch.Generator().manual_seed(1)
    td = TensorDict({"observation": torch.randn(B, T, OBS, generator=g),
                     "next": {"observation": torch.randn(B, T, OBS, generator=g),
                              "reward": torch.randn(B, T, 1, generator=g), "cost": torch.rand(B, T, 1, generator=g),
                              "done": torch.zeros(B, T, 1, dtype=torch.bool),
                              "terminated": torch.zeros(B, T, 1, dtype=torch.bool)}}, [B, T])
    torch.manual_seed(0)
    with torch.no_grad():
        gaussian_actor()(td)
    return td


@dataclass
class Case:
    make: Callable[[], object]
    batch: Callable[[], TensorDict]
    select: tuple[str, ...]  # a subset of out_keys for select_out_keys
    rename: tuple[str, NestedKey]  # set_keys(name=new key): a key forward reads
    supported: ValueEstimators  # make_value_estimator builds this one
    refused: ValueEstimators | None  # and refuses this one (None: ClipPPOLoss takes every estimator TorchRL has)


LOSSES = {
    "PERLHFLoss": Case(perlhf, perlhf_batch, ("loss_qvalue", "loss_actor"),
                       ("behavior_action", ("next", "executed_action")), ValueEstimators.TD0, ValueEstimators.GAE),
    "ProxyValueLoss": Case(proxy_value, perlhf_batch, ("loss_qvalue", "td_loss"),
                           ("behavior_action", ("next", "executed_action")), ValueEstimators.TD0, ValueEstimators.GAE),
    "QEnsembleTDLoss": Case(q_ensemble_td, ensemble_batch, ("loss_qvalue", "q_spread"),
                            ("next_action", ("next", "policy_action")), ValueEstimators.TD0, ValueEstimators.GAE),
    "SACLagLoss": Case(sac_lag, sac_batch, ("loss_actor", "loss_cost_qvalue"), ("cost", "safety_cost"),
                       ValueEstimators.TD0, ValueEstimators.GAE),
    "PPOLagLoss": Case(ppo_lag, trajectory_batch, ("loss_objective", "loss_cost_critic"), ("cost", "safety_cost"),
                       ValueEstimators.GAE, None),
    "CPOLoss": Case(cpo, trajectory_batch, ("loss_cost_critic",), ("cost", "safety_cost"), ValueEstimators.GAE,
                    ValueEstimators.TD0),
}
cases = pytest.mark.parametrize("case", list(LOSSES.values()), ids=list(LOSSES))


def run(loss, *args, **kwargs):
    torch.manual_seed(7)  # the SAC-type losses sample actions
    return loss(*args, **kwargs)


def flat(key: NestedKey) -> str:
    """The keyword ``dispatch`` expects for ``key``: ``("next", "reward")`` -> ``next_reward``."""
    key = unravel_key(key)
    return "_".join(key) if isinstance(key, tuple) else key


def renamed(td: TensorDict, old: NestedKey, new: NestedKey) -> TensorDict:
    td = td.clone(False)
    td.set(new, td.pop(old))
    return td


@cases
def test_repr_and_print_name_the_keys(case, capsys):
    loss = case.make()
    print(loss)
    text = capsys.readouterr().out
    assert text.startswith(type(loss).__name__ + "(")
    assert f"in_keys={loss.in_keys}" in text and f"out_keys={loss.out_keys}" in text


@cases
def test_out_keys_are_what_forward_returns(case):
    loss, batch = case.make(), case.batch()
    out = run(loss, batch)
    assert sorted(out.keys()) == sorted(loss.out_keys)
    assert len(set(loss.out_keys)) == len(loss.out_keys)


@cases
def test_in_keys_are_enough_and_all_in_the_batch(case):
    loss, batch = case.make(), case.batch()
    full = run(loss, batch.clone())
    batch_keys = set(batch.keys(True, True))
    assert set(loss.in_keys) <= batch_keys, set(loss.in_keys) - batch_keys
    only = run(loss, batch.select(*loss.in_keys))
    for key in loss.out_keys:
        torch.testing.assert_close(only[key], full[key], msg=key)


@cases
def test_keyword_call_returns_the_out_keys_in_order(case):
    loss, batch = case.make(), case.batch()
    expected = run(loss, batch.clone())
    values = run(loss, **{flat(key): batch.get(key) for key in loss.in_keys})
    assert isinstance(values, tuple) and len(values) == len(loss.out_keys)
    for key, got in zip(loss.out_keys, values):
        torch.testing.assert_close(got, expected[key], msg=key)


@cases
def test_select_out_keys_narrows_both_call_forms(case):
    loss, batch = case.make(), case.batch()
    expected = run(loss, batch.clone())
    assert loss.select_out_keys(*case.select) is loss
    assert list(loss.out_keys) == list(case.select)
    out = run(loss, batch.clone())
    assert sorted(out.keys()) == sorted(case.select)
    values = run(loss, **{flat(key): batch.get(key) for key in loss.in_keys})
    values = values if isinstance(values, tuple) else (values,)
    assert len(values) == len(case.select)
    for key, got in zip(case.select, values):
        torch.testing.assert_close(got, expected[key], msg=key)
    with pytest.raises((ValueError, RuntimeError)):
        case.make().select_out_keys("loss_that_does_not_exist")


@cases
def test_set_keys_moves_the_in_keys_and_reads_the_renamed_batch(case):
    loss, batch = case.make(), case.batch()
    name, new = case.rename
    old = getattr(loss.tensor_keys, name)
    old_full = unravel_key(("next", old)) if unravel_key(("next", old)) in loss.in_keys else unravel_key(old)
    new_full = unravel_key(("next", new)) if old_full != unravel_key(old) else unravel_key(new)
    expected = run(loss, batch.clone())
    loss.set_keys(**{name: new})
    assert new_full in loss.in_keys and old_full not in loss.in_keys
    out = run(loss, renamed(batch, old_full, new_full))
    for key in loss.out_keys:
        torch.testing.assert_close(out[key], expected[key], msg=key)


@cases
def test_make_value_estimator_builds_the_supported_one_and_refuses_the_others(case):
    loss = case.make()
    loss.make_value_estimator(case.supported, gamma=0.5)
    assert loss.value_type == case.supported
    estimator = loss.value_estimator
    assert isinstance(estimator, {ValueEstimators.TD0: TD0Estimator, ValueEstimators.GAE: GAE}[case.supported])
    assert float(estimator.gamma) == 0.5
    if case.refused is None:
        return
    with pytest.raises(NotImplementedError, match=case.supported.name) as refusal:
        loss.make_value_estimator(case.refused)
    assert "\n" not in str(refusal.value)


@pytest.mark.parametrize("make", [perlhf, cpo], ids=["PERLHFLoss", "CPOLoss"])
def test_our_refusal_is_also_a_value_error_naming_the_allowed_estimators(make):
    loss = make()
    supported = [v.name for v in loss.SUPPORTED_VALUE_ESTIMATORS]
    with pytest.raises(UnsupportedValueEstimator, match=f"allowed: {supported}".replace("[", r"\[")) as refusal:
        loss.make_value_estimator("td_lambda")
    assert isinstance(refusal.value, ValueError) and isinstance(refusal.value, NotImplementedError)


def test_perlhf_td0_gamma_is_the_gamma_its_targets_use():
    """``make_value_estimator(TD0, gamma=g)`` gives the same numbers as a loss built with ``gamma=g``."""
    batch = perlhf_batch()
    changed = perlhf().make_value_estimator(ValueEstimators.TD0, gamma=0.5)
    built, default = perlhf(gamma=0.5), perlhf()
    assert changed.gamma == 0.5
    out_changed, out_built, out_default = run(changed, batch), run(built, batch), run(default, batch)
    for key in changed.out_keys:
        torch.testing.assert_close(out_changed[key], out_built[key], msg=key)
    assert not torch.allclose(out_changed["td_loss"], out_default["td_loss"])


def test_perlhf_in_keys_follow_the_options():
    """Options that read more (a reward, a disturbance cost) or less (no cosine cost) change ``in_keys``."""
    plain = perlhf()
    assert ("next", "reward") not in plain.in_keys and ("next", "intervention_cost") in plain.in_keys
    assert ("next", "reward") in perlhf(use_reward=True).in_keys
    assert ("next", "intervention_cost") not in perlhf(cosine_cost=False).in_keys
    torch.manual_seed(0)
    haim = PERLHFLoss(make_actor(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)), make_qvalue(OBS, ACT, (16,)),
                      make_qvalue(OBS, ACT, (16,)))
    assert ("next", "disturbance_cost") in haim.in_keys
    assert {"loss_disturbance_qvalue", "q_disturbance"} <= set(haim.out_keys)
