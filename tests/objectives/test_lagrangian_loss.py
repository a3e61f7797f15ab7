"""Tests of the Lagrangian safe-RL losses: ``LagrangeMultiplier``, ``SACLagLoss`` and ``PPOLagLoss``.

Known answers: the multiplier's projected dual ascent is checked step by step; the cost critic is fitted
on a deterministic chain whose discounted cost-to-go is closed form; the cost GAE target on a trajectory
with cost 1 per step is the discounted count of remaining steps; on a bandit where the high-reward
action also costs (``r(a) = 0.9 + 0.1 a``, ``c(a) = (1 + a) / 2``: reward 1 / cost 1 at ``a = 1``, reward
0.8 / cost 0 at ``a = -1``) the policy moves to the costly end with ``lambda = 0`` and to the safe end with
a large ``lambda``. Every comparison of two sampling calls fixes ``torch.manual_seed`` before each.
"""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal
from torchrl.objectives import ClipPPOLoss, SACLoss, SoftUpdate

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives.lagrangian import LagrangeMultiplier, PPOLagLoss, SACLagLoss

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore:No target network updater")]

OBS, ACT, BATCH, HIDDEN = 3, 2, 16, (16,)
SAC_LOSS_KEYS = ("loss_actor", "loss_qvalue", "loss_cost_qvalue", "loss_alpha")


# --------------------------------------------------------------------------- helpers

def sac_batch(batch: int = BATCH, obs: int = OBS, act: int = ACT, seed: int = 1) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.randn(batch, obs, generator=g),
        "action": torch.rand(batch, act, generator=g) * 2 - 1,
        "next": {"observation": torch.randn(batch, obs, generator=g),
                 "reward": torch.randn(batch, 1, generator=g),
                 "cost": torch.rand(batch, 1, generator=g),
                 "done": torch.zeros(batch, 1, dtype=torch.bool),
                 "terminated": torch.zeros(batch, 1, dtype=torch.bool)},
    }, [batch])


def make_sac_lag(seed: int = 0, lam: float = 0.0, **kwargs) -> SACLagLoss:
    torch.manual_seed(seed)
    return SACLagLoss(make_actor(OBS, ACT, HIDDEN), make_qvalue(OBS, ACT, HIDDEN), make_qvalue(OBS, ACT, HIDDEN),
                      lagrange_multiplier=LagrangeMultiplier(init=lam), **kwargs)


class LinearQ(nn.Module):
    """``Q(s, a) = w . [s, a] + b``: represents a tabular value over one-hot states exactly."""

    def __init__(self, obs: int, act: int):
        super().__init__()
        self.linear = nn.Linear(obs + act, 1)
        nn.init.zeros_(self.linear.weight)
        nn.init.zeros_(self.linear.bias)

    def forward(self, observation, action):
        return self.linear(torch.cat([observation, action], -1))


def ppo_actor(obs: int = OBS, act: int = ACT) -> ProbabilisticActor:
    net = nn.Sequential(MLP(in_features=obs, out_features=2 * act, num_cells=list(HIDDEN)), NormalParamExtractor())
    return ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"],
                              distribution_class=TanhNormal, return_log_prob=True)


def value_net(out_key: str, obs: int = OBS) -> TensorDictModule:
    return TensorDictModule(MLP(in_features=obs, out_features=1, num_cells=list(HIDDEN)), ["observation"], [out_key])


def make_ppo_pair(lam: float, seed: int = 0, **kwargs) -> tuple[PPOLagLoss, ClipPPOLoss]:
    """A ``PPOLagLoss`` and a ``ClipPPOLoss`` sharing the same actor and reward critic weights."""
    torch.manual_seed(seed)
    actor, critic = ppo_actor(), value_net("state_value")
    lag = PPOLagLoss(actor, critic, value_net("state_cost_value"),
                     lagrange_multiplier=LagrangeMultiplier(init=lam), **kwargs)
    return lag, ClipPPOLoss(copy.deepcopy(actor), copy.deepcopy(critic), **kwargs)


def ppo_batch(batch: int = 4, time: int = 5, seed: int = 1, actor=None) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({
        "observation": torch.randn(batch, time, OBS, generator=g),
        "next": {"observation": torch.randn(batch, time, OBS, generator=g),
                 "reward": torch.randn(batch, time, 1, generator=g),
                 "cost": torch.rand(batch, time, 1, generator=g),
                 "done": torch.zeros(batch, time, 1, dtype=torch.bool),
                 "terminated": torch.zeros(batch, time, 1, dtype=torch.bool)},
    }, [batch, time])
    with torch.no_grad():
        (actor or ppo_actor())(td)
    return td


# --------------------------------------------------------------------------- the multiplier

def test_multiplier_rises_while_cost_exceeds_limit_and_falls_back_to_exactly_zero():
    lam = LagrangeMultiplier(cost_limit=1.0, lr=0.1)
    values = [lam.update(3.0).item() for _ in range(5)]  # violation 2 per step: +0.2 each
    assert values == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0], abs=1e-6)
    values = [lam.update(0.0).item() for _ in range(15)]  # below the limit: -0.1 per step, clipped at 0
    assert values[:9] == pytest.approx([0.9 - 0.1 * i for i in range(9)], abs=1e-6)
    assert values[-5:] == [0.0] * 5
    assert lam.update(1.0).item() == 0.0  # exactly at the limit: no change


def test_multiplier_max_value_state_dict_and_gradient_form_agree():
    lam = LagrangeMultiplier(cost_limit=2.0, lr=0.5, max_value=1.0)
    for _ in range(10):
        lam.update(5.0)
    assert lam.value.item() == 1.0
    restored = LagrangeMultiplier()
    restored.load_state_dict(lam.state_dict())
    assert restored.value.item() == 1.0 and restored.cost_limit.item() == 2.0

    manual, optimised = LagrangeMultiplier(lr=0.05, init=0.3), LagrangeMultiplier(init=0.3)
    optimiser = torch.optim.SGD(optimised.parameters(), lr=0.05)
    for cost in (3.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0):
        manual.update(cost)
        optimiser.zero_grad()
        optimised.loss(cost).backward()
        optimiser.step()
        optimised.project_()
        assert optimised.value.item() == pytest.approx(manual.value.item(), abs=1e-6)


@pytest.mark.parametrize("parametrization", ["softplus", "log"])
def test_smooth_parametrizations_stay_positive_and_follow_the_violation(parametrization):
    lam = LagrangeMultiplier(init=1.0, lr=0.5, parametrization=parametrization)
    assert lam.value.item() == pytest.approx(1.0)
    up = [lam.update(3.0).item() for _ in range(5)]
    assert all(b > a for a, b in zip([1.0, *up], up))
    down = [lam.update(0.0).item() for _ in range(50)]
    assert all(b < a for a, b in zip([up[-1], *down], down)) and down[-1] > 0
    with pytest.raises(ValueError):
        LagrangeMultiplier(init=0.0, parametrization=parametrization)


# --------------------------------------------------------------------------- SACLagLoss

def test_sac_lag_outputs_keys_and_gradient_routing():
    loss = make_sac_lag(lam=0.5)
    td = sac_batch()
    before = td.clone()
    out = loss(td)
    for key in (*SAC_LOSS_KEYS, "alpha", "entropy", "lagrange_multiplier", "cost_qvalue"):
        assert out[key].shape == () and torch.isfinite(out[key]), key
    assert set(loss.out_keys) >= {*SAC_LOSS_KEYS, "lagrange_multiplier"}
    assert {("next", "cost"), ("next", "reward"), ("next", "terminated"), "observation", "action"} <= set(loss.in_keys)
    assert out["lagrange_multiplier"].item() == pytest.approx(0.5)
    assert (td.select(*before.keys(True, True)) == before).all()  # the batch's own entries are untouched

    out["loss_cost_qvalue"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0
               for p in loss.cost_qvalue_network_params.values(True, True))
    assert all(p.grad is None for p in loss.qvalue_network_params.values(True, True))
    assert all(p.grad is None for p in loss.actor_network_params.values(True, True))
    loss.zero_grad()
    out = loss(td)
    out["loss_actor"].backward()  # the penalty reaches the actor, not the (detached) cost critic
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in loss.cost_qvalue_network_params.values(True, True))
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.actor_network_params.values(True, True))
    assert loss.lagrange_multiplier.raw.grad is None  # lambda moves only through its own update

    updater = SoftUpdate(loss, eps=0.5)  # finds the cost critic's target nets by their name
    target_before = loss.target_cost_qvalue_network_params.data.clone()
    for p in loss.cost_qvalue_network_params.values(True, True):
        p.data.add_(1.0)
    updater.step()
    for key, target in loss.target_cost_qvalue_network_params.items(True, True):
        torch.testing.assert_close(target, target_before.get(key) + 0.5)


def test_sac_lag_with_lambda_zero_is_exactly_sac():
    td = sac_batch()
    torch.manual_seed(0)
    actor, q = make_actor(OBS, ACT, HIDDEN), make_qvalue(OBS, ACT, HIDDEN)
    cost_q = make_qvalue(OBS, ACT, HIDDEN)
    torch.manual_seed(5)  # SACLoss resamples its twin critics at construction: same seed, same critics
    sac = SACLoss(copy.deepcopy(actor), copy.deepcopy(q))
    torch.manual_seed(5)
    lag = SACLagLoss(actor, q, cost_q)
    assert (sac.qvalue_network_params.data == lag.qvalue_network_params.data).all()
    torch.manual_seed(7)
    expected = sac(td.clone())
    torch.manual_seed(7)
    got = lag(td.clone())
    for key in ("loss_actor", "loss_qvalue", "loss_alpha", "entropy"):
        assert torch.equal(got[key], expected[key]), key
    expected["loss_actor"].backward()
    got["loss_actor"].backward()
    for key, p in lag.actor_network_params.items(True, True):
        assert torch.equal(p.grad, sac.actor_network_params.get(key).grad), key

    lag.lagrange_multiplier.raw.data.fill_(2.0)  # and the penalty changes it
    torch.manual_seed(7)
    penalised = lag(td.clone())
    assert not torch.allclose(penalised["loss_actor"], expected["loss_actor"])
    assert torch.equal(penalised["loss_qvalue"], expected["loss_qvalue"])


def test_sac_lag_actor_penalty_is_the_normalised_lagrangian():
    """With constant critics ``Q = 2`` and ``Q_c = 3`` the actor loss is ``(alpha log pi - 2 + 3 lam) / (1 + lam)``."""

    class Constant(nn.Module):
        def __init__(self, value):
            super().__init__()
            self.value = nn.Parameter(torch.tensor(float(value)))

        def forward(self, observation, action):
            return self.value.expand(*observation.shape[:-1], 1)

    def critic(value):
        return TensorDictModule(Constant(value), ["observation", "action"], ["state_action_value"])

    td, lam = sac_batch(), 1.5
    for normalize in (True, False):
        torch.manual_seed(0)
        loss = SACLagLoss(make_actor(OBS, ACT, HIDDEN), critic(2.0), critic(3.0), fixed_alpha=True, alpha_init=0.1,
                          lagrange_multiplier=LagrangeMultiplier(init=lam), normalize_actor_loss=normalize)
        torch.manual_seed(3)
        out = loss(td)
        log_prob = -out["entropy"]  # entropy = -mean log pi of the same sample
        expected = 0.1 * log_prob - 2.0 + lam * 3.0
        assert out["loss_actor"].item() == pytest.approx((expected / (1 + lam) if normalize else expected).item(),
                                                         abs=1e-5)
        assert out["cost_qvalue"].item() == pytest.approx(3.0)


def test_sac_lag_cost_critic_converges_to_the_discounted_cost_of_a_chain():
    """Chain ``s_0 -> ... -> s_4`` (one-hot), cost 1 per step, terminal after ``s_4``:
    ``Q_c(s_i, .) = (1 - gamma^(5 - i)) / (1 - gamma)``; the reward is 0 and only the cost critic is trained."""
    states, gamma = 5, 0.9
    obs = torch.eye(states)
    next_obs = torch.cat([obs[1:], torch.zeros(1, states)])
    terminated = torch.zeros(states, 1, dtype=torch.bool)
    terminated[-1] = True
    td = TensorDict({"observation": obs, "action": torch.zeros(states, 1),
                     "next": {"observation": next_obs, "reward": torch.zeros(states, 1), "cost": torch.ones(states, 1),
                              "done": terminated.clone(), "terminated": terminated}}, [states])
    torch.manual_seed(0)
    loss = SACLagLoss(make_actor(states, 1, HIDDEN), make_qvalue(states, 1, HIDDEN),
                      TensorDictModule(LinearQ(states, 1), ["observation", "action"], ["state_action_value"]),
                      loss_function="l2")
    loss.make_value_estimator(gamma=gamma)
    updater = SoftUpdate(loss, eps=0.8)
    optimiser = torch.optim.Adam(loss.cost_qvalue_network_params.values(True, True), lr=0.05)
    for _ in range(400):
        optimiser.zero_grad()
        loss.cost_qvalue_loss(td).backward()
        optimiser.step()
        updater.step()
    expected = torch.tensor([(1 - gamma ** (states - i)) / (1 - gamma) for i in range(states)])
    values = loss._vmap_cost_qnetworkN0(td.select("observation", "action"), loss.cost_qvalue_network_params)
    values = values["state_action_value"].squeeze(-1)  # (2 critics, 5 states)
    torch.testing.assert_close(values, expected.expand_as(values), atol=0.02, rtol=0)


def bandit_policy_mean(lam: float, steps: int = 150, seed: int = 0) -> float:
    """Train SAC-Lag (critics and actor, fixed ``lambda``) on the one-step bandit ``r = 0.9 + 0.1 a``,
    ``c = (1 + a) / 2`` from uniformly drawn actions (off-policy data covering the whole range); return
    the deterministic action. Break-even: ``lambda = 0.1 / 0.5 = 0.2``."""
    torch.manual_seed(seed)
    loss = SACLagLoss(make_actor(1, 1, HIDDEN), make_qvalue(1, 1, HIDDEN), make_qvalue(1, 1, HIDDEN),
                      fixed_alpha=True, alpha_init=0.01, loss_function="l2",
                      lagrange_multiplier=LagrangeMultiplier(init=lam))
    optimiser = torch.optim.Adam(loss.parameters(), lr=3e-2)
    batch, obs = 64, torch.zeros(64, 1)
    done = torch.ones(batch, 1, dtype=torch.bool)
    for _ in range(steps):
        action = torch.rand(batch, 1) * 2 - 1
        td = TensorDict({"observation": obs, "action": action,
                         "next": {"observation": obs, "reward": 0.9 + 0.1 * action, "cost": (1 + action) / 2,
                                  "done": done, "terminated": done}}, [batch])
        out = loss(td)
        optimiser.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optimiser.step()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return loss.actor_network(TensorDict({"observation": obs[:1]}, [1]))["action"].item()


@pytest.mark.parametrize("lam", [0.0, 0.1])
def test_sac_lag_small_lambda_keeps_the_high_reward_costly_action(lam):
    assert bandit_policy_mean(lam) > 0.5


@pytest.mark.parametrize("lam", [0.3, 5.0])
def test_sac_lag_large_lambda_moves_the_policy_to_the_safe_action(lam):
    assert bandit_policy_mean(lam) < -0.5


# --------------------------------------------------------------------------- PPOLagLoss

def test_ppo_lag_with_lambda_zero_is_exactly_clip_ppo_and_outputs_its_keys():
    lag, ppo = make_ppo_pair(lam=0.0)
    td = ppo_batch(actor=lag.actor_network)
    torch.manual_seed(2)  # TanhNormal's entropy is a Monte-Carlo estimate
    out = lag(td)
    torch.manual_seed(2)
    expected = ppo(td)
    for key in expected.keys(include_nested=True, leaves_only=True):
        assert torch.equal(out[key], expected[key]), key
    for key in ("loss_cost_critic", "lagrange_multiplier"):
        assert out[key].shape == () and torch.isfinite(out[key])
    assert set(lag.out_keys) >= {"loss_objective", "loss_critic", "loss_entropy", "loss_cost_critic"}
    assert ("next", "cost") in lag.in_keys
    assert td.get("cost_advantage", None) is None and td.get("advantage", None) is None  # input not written


def test_ppo_lag_objective_uses_the_penalised_advantage():
    lam = 3.0
    lag, ppo = make_ppo_pair(lam=lam)
    td = ppo_batch(actor=lag.actor_network)
    g = torch.Generator().manual_seed(4)
    td["advantage"], td["cost_advantage"] = torch.randn(4, 5, 1, generator=g), torch.randn(4, 5, 1, generator=g)
    td["value_target"], td["cost_value_target"] = torch.randn(4, 5, 1, generator=g), torch.randn(4, 5, 1, generator=g)
    reference = td.clone()
    reference["advantage"] = (td["advantage"] - lam * td["cost_advantage"]) / (1 + lam)
    out, expected = lag(td), ppo(reference)
    assert torch.equal(out["loss_objective"], expected["loss_objective"])
    assert torch.equal(out["loss_critic"], expected["loss_critic"])
    assert out["lagrange_multiplier"].item() == lam
    out["loss_cost_critic"].backward()
    assert all(p.grad is not None for p in lag.cost_critic_network_params.values(True, True))
    assert all(p.grad is None for p in lag.actor_network_params.values(True, True))


def test_ppo_lag_cost_gae_reads_the_cost_with_the_reward_estimator_hyperparameters():
    """Cost 1 per step, terminal at the last of 4 steps, a zero cost critic and ``lmbda = 1``: the cost value
    target is ``sum_k gamma^k`` over the remaining steps, whatever the reward."""
    lag, _ = make_ppo_pair(lam=0.0)
    lag.make_value_estimator(gamma=0.5, lmbda=1.0)
    for p in lag.cost_critic_network_params.values(True, True):
        p.data.zero_()
    td = ppo_batch(batch=2, time=4, actor=lag.actor_network)
    td["next", "cost"] = torch.ones(2, 4, 1)
    td["next", "terminated"][:, -1] = True
    td["next", "done"][:, -1] = True
    lag.cost_value_estimator(td, params=lag.cost_critic_network_params.detach())
    expected = torch.tensor([1.875, 1.75, 1.5, 1.0]).view(1, 4, 1).expand(2, 4, 1)
    torch.testing.assert_close(td["cost_value_target"], expected)
    torch.testing.assert_close(td["cost_advantage"], expected)  # V_c = 0


def test_ppo_lag_large_lambda_moves_the_policy_to_lower_cost():
    """One batch with fixed advantages ``A = 0.1 a``, ``A_c = 0.5 a`` (``a``: first action dim, so the cost grows
    with ``a``). After a few steps on the loss, the importance-weighted mean ``mean(ratio * a)`` (the batch's
    estimate of ``E_pi_new[a]``) rises above ``mean(a)`` with ``lambda = 0`` and falls below it with ``lambda = 5``."""

    def weighted_action_shift(lam: float) -> float:
        lag, _ = make_ppo_pair(lam=lam, entropy_coeff=0.0)
        td = ppo_batch(batch=64, time=1, actor=lag.actor_network)
        action = td["action"][..., :1]
        td["advantage"], td["cost_advantage"] = 0.1 * action, 0.5 * action
        td["value_target"], td["cost_value_target"] = torch.zeros_like(action), torch.zeros_like(action)
        optimiser = torch.optim.Adam(lag.actor_network_params.values(True, True), lr=1e-2)
        for _ in range(5):
            optimiser.zero_grad()
            lag(td)["loss_objective"].backward()
            optimiser.step()
        with torch.no_grad(), lag.actor_network_params.to_module(lag.actor_network):
            log_prob = lag.actor_network.get_dist(td.select("observation")).log_prob(td["action"])
        ratio = (log_prob - td["action_log_prob"]).exp().unsqueeze(-1)
        return ((ratio * action).mean() - action.mean()).item()

    assert weighted_action_shift(0.0) > 0.03
    assert weighted_action_shift(5.0) < -0.03


class ConstantCostQ(nn.Module):
    """``Q_c(s, a) = b`` (one parameter): copies of it hold distinct values when their ``b`` differ."""

    def __init__(self):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(1))

    def forward(self, observation, action):
        return self.bias.expand(*observation.shape[:-1], 1)


@pytest.mark.parametrize("aggregate, picked", [("max", 3.0), ("min", 1.0), ("mean", 2.0)])
def test_sac_lag_cost_target_aggregates_distinct_target_copies(aggregate, picked):
    """Issue 45, case 10: target cost critics holding different values (1 and 3); the TD target takes the one
    ``cost_aggregate`` names (``max``, the default: pessimistic about cost), derived by hand."""
    gamma = 0.9
    torch.manual_seed(0)
    loss = SACLagLoss(make_actor(OBS, ACT, HIDDEN), make_qvalue(OBS, ACT, HIDDEN),
                      TensorDictModule(ConstantCostQ(), ["observation", "action"], ["state_action_value"]),
                      loss_function="l2", cost_aggregate=aggregate)
    loss.make_value_estimator(gamma=gamma)
    for value in loss.target_cost_qvalue_network_params.values(True, True):
        value.data.copy_(torch.tensor([[1.0], [3.0]]).reshape(value.shape))
    batch = sac_batch()
    cost = batch["next", "cost"].squeeze(-1)
    target = cost + gamma * picked  # the online copies are 0: each one's squared error is target ** 2
    expected = 2 * (target ** 2).mean()
    torch.testing.assert_close(loss.cost_qvalue_loss(batch), expected)
