"""Tests of ``PERLHFLoss``: outputs, gradient routing, the gap, targets, flags, and a tiny learning task.

Exact checks use hand-built critics whose value is known in closed form (``ConstantQ``:
``Q(s, a) = v``; ``BehaviorSideQ``: ``Q(s, a) = w * max(a[0], 0)``), so the expected TD and gap
terms are computed by hand. The loss samples actions from the actor, so every comparison of two
calls fixes ``torch.manual_seed`` before each call.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SoftUpdate

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import PERLHFLoss
from pe_rlhf.objectives.perlhf import make_transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")

OBS_DIM, ACTION_DIM, BATCH = 4, 2, 32
HIDDEN = (16, 16)
LOSS_KEYS = ("loss_qvalue", "loss_intervention_qvalue", "loss_actor", "loss_alpha")
DIAGNOSTIC_KEYS = ("alpha", "entropy", "td_loss", "gap_loss", "q_behavior", "q_agent", "q_intervention",
                   "intervention_rate", "failure_rate", "q_failure")
PARAM_GROUPS = ("actor_network_params", "qvalue_network_params", "intervention_qvalue_network_params",
                "log_alpha")


# --------------------------------------------------------------------------- helpers


class ConstantQ(nn.Module):
    """``Q(s, a) = value`` (one scalar parameter): the TD target is known in closed form."""

    def __init__(self, value: float = 0.0):
        super().__init__()
        self.value = nn.Parameter(torch.tensor(float(value)))

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.value.expand(*observation.shape[:-1], 1)


class BehaviorSideQ(nn.Module):
    """``Q(s, a) = weight * max(a[0], 0)``: raising ``weight`` raises Q only at positive steering."""

    def __init__(self, weight: float = 0.0):
        super().__init__()
        self.weight = nn.Parameter(torch.tensor(float(weight)))

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.weight * action[..., :1].clamp(min=0)


def critic(net: nn.Module) -> TensorDictModule:
    return TensorDictModule(net, in_keys=["observation", "action"], out_keys=["state_action_value"])


def make_loss(qvalue=None, intervention_qvalue=None, seed: int = 0, **kwargs) -> PERLHFLoss:
    """A loss with twin intervention critics (the authors' code), so the min over copies is exercised;
    the default single critic (the paper) has its own test. Failure rows' target is the usual terminal 0
    (``failure_target="zero"``), which the closed-form targets below assume; ``batch_min``, the default, has its
    own tests."""
    kwargs.setdefault("num_intervention_qvalue_nets", 2)
    kwargs.setdefault("failure_target", "zero")
    torch.manual_seed(seed)
    actor = make_actor(OBS_DIM, ACTION_DIM, HIDDEN)
    qvalue = qvalue if qvalue is not None else make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN)
    intervention_qvalue = (intervention_qvalue if intervention_qvalue is not None
                           else make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN))
    return PERLHFLoss(actor, qvalue, intervention_qvalue, **kwargs)


def make_batch(batch: int = BATCH, intervention=0.5, start=None, terminated=False, seed: int = 1,
               shape: tuple[int, ...] | None = None) -> TensorDict:
    """A batch with every key the loss reads. ``intervention``/``terminated``: a probability or a bool
    tensor ``(B, 1)``; ``start`` defaults to ``intervention`` (every takeover row is a start)."""
    g = torch.Generator().manual_seed(seed)

    def flags(value):
        if isinstance(value, torch.Tensor):
            return value.bool()
        return torch.rand(batch, 1, generator=g) < float(value)

    intervention = flags(intervention)
    start = intervention if start is None else flags(start) & intervention
    agent = torch.rand(batch, ACTION_DIM, generator=g) * 2 - 1
    behavior = torch.where(intervention, torch.rand(batch, ACTION_DIM, generator=g) * 2 - 1, agent)
    terminated = flags(terminated)
    td = make_transitions(torch.randn(batch, OBS_DIM, generator=g), torch.randn(batch, OBS_DIM, generator=g),
                          agent, behavior, intervention, start, terminated, torch.randn(batch, 1, generator=g))
    return td.reshape(*shape) if shape is not None else td


def run(loss: PERLHFLoss, batch: TensorDict, seed: int = 123) -> TensorDict:
    torch.manual_seed(seed)
    return loss(batch.clone())


def set_online(params, name: str, values) -> None:
    """Overwrite the online copies of a hand-built critic's scalar parameter (targets untouched)."""
    params.get(("module", name)).data.copy_(torch.as_tensor(values, dtype=torch.float32))


def grad_groups(loss: PERLHFLoss) -> dict[str, list[bool]]:
    """Per parameter group: for each tensor, whether it received a non-zero gradient."""
    out: dict[str, list[bool]] = {}
    for name, p in loss.named_parameters():
        out.setdefault(name.split(".")[0], []).append(p.grad is not None and bool(p.grad.abs().sum() > 0))
    return out


def actor_action(loss: PERLHFLoss, obs: torch.Tensor, mode=ExplorationType.DETERMINISTIC) -> torch.Tensor:
    with torch.no_grad(), set_exploration_type(mode), loss.actor_network_params.to_module(loss.actor_network):
        return loss.actor_network(TensorDict({"observation": obs}, obs.shape[:1])).get("action")


def q_values(loss: PERLHFLoss, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``(num_qvalue_nets, B)`` online proxy-Q values."""
    values = []
    with torch.no_grad():
        for k in range(loss.num_qvalue_nets):
            with loss.qvalue_network_params[k].to_module(loss.qvalue_network):
                td = loss.qvalue_network(TensorDict({"observation": obs, "action": action}, obs.shape[:1]))
            values.append(td.get("state_action_value").squeeze(-1))
    return torch.stack(values)


# --------------------------------------------------------------------------- outputs


def test_output_keys_shapes_and_grads():
    out = run(make_loss(), make_batch())
    assert set(out.keys()) == set(LOSS_KEYS) | set(DIAGNOSTIC_KEYS)
    for key in LOSS_KEYS + DIAGNOSTIC_KEYS:
        assert out[key].shape == torch.Size([]), key
        assert torch.isfinite(out[key]), key
    for key in LOSS_KEYS:
        assert out[key].requires_grad, key
    for key in DIAGNOSTIC_KEYS:
        assert not out[key].requires_grad, key
    assert out["alpha"] == pytest.approx(1.0)
    assert out["td_loss"] + out["gap_loss"] == pytest.approx(out["loss_qvalue"].item(), rel=1e-5, abs=1e-6)


def test_input_batch_is_not_modified():
    batch = make_batch()
    before = {k: v.clone() for k, v in batch.items(True, True)}
    torch.manual_seed(0)
    make_loss()(batch)
    after = dict(batch.items(True, True))
    assert set(after) == set(before)
    for k, v in before.items():
        assert torch.equal(after[k], v), k


@pytest.mark.parametrize(
    "key, group",
    [("loss_qvalue", "qvalue_network_params"),
     ("loss_intervention_qvalue", "intervention_qvalue_network_params"),
     ("loss_actor", "actor_network_params"),
     ("loss_alpha", "log_alpha")],
)
def test_each_loss_only_reaches_its_own_parameters(key, group):
    loss = make_loss()
    assert {name.split(".")[0] for name, _ in loss.named_parameters()} == set(PARAM_GROUPS)
    for p in loss.parameters():
        p.grad = None
    run(loss, make_batch())[key].backward()
    groups = grad_groups(loss)
    assert all(groups[group]), f"{key}: some {group} tensors got no gradient"
    for other in PARAM_GROUPS:
        if other != group:
            assert not any(groups[other]), f"{key} leaked a gradient into {other}"
    for name, buffer in loss.named_buffers():  # targets are buffers: never part of a graph
        assert buffer.grad is None and not buffer.requires_grad, name


# --------------------------------------------------------------------------- the gap


def test_gap_is_exact_and_raising_q_at_the_mentor_action_lowers_loss_qvalue():
    # Every row a takeover: the agent steers left (-0.5), the mentor right (+0.7).
    batch = make_batch(intervention=1.0)
    batch["action"][:, 0] = -0.5
    batch["next", "behavior_action"][:, 0] = 0.7
    loss = make_loss(critic(BehaviorSideQ(0.0)), critic(ConstantQ(0.0)))
    base = run(loss, batch)
    assert base["gap_loss"] == 0
    set_online(loss.qvalue_network_params, "weight", [1.0, 2.0])  # Q(s, a_exec) = 0.7 w, Q(s, a_AV) = 0
    raised = run(loss, batch)
    assert raised["q_behavior"] == pytest.approx(0.7 * 1.5)
    assert raised["q_agent"] == pytest.approx(0.0)
    # gap_coef * sum_k mean(I * (Q_k(s, a_AV) - Q_k(s, a_exec))) = 10 * (0 - 0.7 * (1 + 2))
    assert raised["gap_loss"] == pytest.approx(-21.0, rel=1e-5)
    assert raised["loss_qvalue"] < base["loss_qvalue"]


def test_gap_counts_only_takeover_rows():
    intervention = (torch.arange(BATCH) % 4 == 0).unsqueeze(-1)  # a quarter of the rows
    batch = make_batch(intervention=intervention)
    batch["action"][:, 0] = -0.5
    batch["next", "behavior_action"][:, 0] = torch.where(intervention.squeeze(-1), 0.7, 0.3)
    loss = make_loss(critic(BehaviorSideQ(0.0)), critic(ConstantQ(0.0)), gap_coef=4.0)
    set_online(loss.qvalue_network_params, "weight", [1.0, 3.0])
    out = run(loss, batch)
    assert out["gap_loss"] == pytest.approx(4.0 * 0.25 * (0 - 0.7 * 4.0), rel=1e-5)
    assert out["intervention_rate"] == pytest.approx(0.25)


def test_gradient_step_on_the_gap_separates_mentor_and_agent_values():
    batch = make_batch(intervention=1.0, seed=5)
    loss = make_loss(seed=3)
    before = run(loss, batch)
    params = list(loss.qvalue_network_params.values(True, True))
    grads = torch.autograd.grad(before["loss_qvalue"], params)
    with torch.no_grad():
        for p, g in zip(params, grads):
            p -= 1e-3 * g
    after = run(loss, batch)
    assert after["loss_qvalue"] < before["loss_qvalue"]
    assert after["q_behavior"] > before["q_behavior"]
    assert (after["q_behavior"] - after["q_agent"]) > (before["q_behavior"] - before["q_agent"])


def test_no_takeover_means_no_gap():
    loss = make_loss()
    out = run(loss, make_batch(intervention=0.0))
    assert out["gap_loss"] == 0
    assert out["intervention_rate"] == 0
    assert out["q_agent"] == 0 and torch.isfinite(out["q_agent"])  # empty selection, no NaN
    assert torch.equal(out["loss_qvalue"].detach(), out["td_loss"])
    out["loss_qvalue"].backward()
    assert all(grad_groups(loss)["qvalue_network_params"])


# --------------------------------------------------------------------------- targets and reward


def test_reward_is_ignored_unless_use_reward():
    batch = make_batch()
    other = batch.clone()
    other["next", "reward"] = other["next", "reward"] * 7 + 3
    loss = make_loss()
    a, b = run(loss, batch), run(loss, other)
    for key in LOSS_KEYS + DIAGNOSTIC_KEYS:
        assert torch.equal(a[key], b[key]), key
    rewarded = make_loss(use_reward=True)
    a, b = run(rewarded, batch), run(rewarded, other)
    assert not torch.equal(a["loss_qvalue"], b["loss_qvalue"])
    assert torch.equal(a["loss_intervention_qvalue"], b["loss_intervention_qvalue"])


@pytest.mark.parametrize("use_reward", [False, True])
def test_terminal_td_target_is_zero_or_the_reward(use_reward):
    batch = make_batch(terminated=1.0)
    loss = make_loss(critic(ConstantQ(5.0)), critic(ConstantQ(5.0)), use_reward=use_reward)
    set_online(loss.qvalue_network_params, "value", [1.5, -2.0])  # targets stay at 5: unused when terminal
    out = run(loss, batch)
    y = batch["next", "reward"].squeeze(-1) if use_reward else torch.zeros(BATCH)
    expected = 0.5 * sum(((c - y) ** 2).mean() for c in (1.5, -2.0))
    assert out["gap_loss"] == 0  # constant critics: Q(s, a_AV) == Q(s, a_exec)
    assert out["td_loss"] == pytest.approx(expected.item(), rel=1e-6)
    assert out["loss_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)


def test_non_terminal_td_target_bootstraps_from_the_target_critics():
    terminated = (torch.arange(BATCH) % 2 == 0).unsqueeze(-1)
    batch = make_batch(terminated=terminated)
    batch["next", "done"] = torch.ones(BATCH, 1, dtype=torch.bool)  # truncated rows still bootstrap
    gamma = 0.9
    # alpha ~ 0 so that y = gamma * (1 - terminated) * min_k Q'_k = gamma * (1 - terminated) * 5.
    loss = make_loss(critic(ConstantQ(5.0)), critic(ConstantQ(0.0)), gamma=gamma, alpha_init=1e-9, fixed_alpha=True)
    set_online(loss.qvalue_network_params, "value", [1.0, 2.0])
    out = run(loss, batch)
    y = gamma * 5.0 * (~terminated.squeeze(-1)).float()
    expected = 0.5 * sum(((c - y) ** 2).mean() for c in (1.0, 2.0))
    assert out["td_loss"] == pytest.approx(expected.item(), rel=1e-5)


def test_td_target_subtracts_the_entropy_of_the_next_action():
    # next state == state and constant critics: the loss draws two actor samples (next, current) from
    # the same distribution; whichever it used for the target, y = gamma * (Q' - alpha * log pi(a'|s')).
    batch = make_batch(terminated=0.0)
    batch["next", "observation"] = batch["observation"].clone()
    gamma, alpha = 0.9, 0.5
    loss = make_loss(critic(ConstantQ(3.0)), critic(ConstantQ(0.0)), gamma=gamma, alpha_init=alpha, fixed_alpha=True)
    set_online(loss.qvalue_network_params, "value", [1.0, 2.0])
    torch.manual_seed(11)
    draws = []
    with set_exploration_type(ExplorationType.RANDOM), loss.actor_network_params.to_module(loss.actor_network):
        for _ in range(2):
            dist = loss.actor_network.get_dist(TensorDict({"observation": batch["observation"]}, [BATCH]))
            _, log_prob = dist.rsample_and_log_prob()
            draws.append((log_prob.sum(-1) if log_prob.shape == (BATCH, ACTION_DIM) else log_prob).detach())
    out = run(loss, batch, seed=11)

    def td(log_prob):
        y = gamma * (3.0 - alpha * log_prob)
        return (0.5 * sum(((c - y) ** 2).mean() for c in (1.0, 2.0))).item()

    matches = [(td(draws[i]), -draws[1 - i].mean().item()) for i in range(2)]
    assert any(out["td_loss"].item() == pytest.approx(t, rel=1e-5)
               and out["entropy"].item() == pytest.approx(h, rel=1e-5)
               for t, h in matches), (out["td_loss"], out["entropy"], matches)


class FixedGaussian(nn.Module):
    """``loc = m``, ``scale = s`` for every state (two scalar parameters): a saturated actor when ``m`` is large."""

    def __init__(self, loc: float, scale: float):
        super().__init__()
        self.loc = nn.Parameter(torch.tensor(float(loc)))
        self.scale = nn.Parameter(torch.tensor(float(scale)))

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        shape = (*observation.shape[:-1], ACTION_DIM)
        return self.loc.expand(shape), self.scale.expand(shape)


def saturated_loss(loc: float = 10.0, scale: float = 1.0) -> PERLHFLoss:
    from torchrl.data import Bounded
    from torchrl.modules import ProbabilisticActor, TanhNormal

    module = TensorDictModule(FixedGaussian(loc, scale), in_keys=["observation"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(module, in_keys=["loc", "scale"], spec=Bounded(-1.0, 1.0, (ACTION_DIM,)),
                               distribution_class=TanhNormal, distribution_kwargs={"low": -1.0, "high": 1.0})
    return PERLHFLoss(actor, critic(ConstantQ(0.0)), critic(ConstantQ(0.0)), alpha_init=1.0, fixed_alpha=True,
                      action_dim=ACTION_DIM)


def test_a_saturated_actor_is_scored_at_its_own_pre_tanh_draw():
    """Pre-tanh mean 10, scale 1: every action rounds to 1 - 1e-6, and inverting it would score each draw
    as if it were ~7.25. The entropy must be the TanhNormal's own, computed in float64 from its closed form
    ``H = 0.5 log(2 pi e s^2) + E[log(1 - tanh(u)^2)]`` per dimension (u ~ N(10, 1)), and the actor's
    gradient must widen the scale (more entropy lowers ``alpha * log pi``)."""
    loss = saturated_loss(10.0, 1.0)
    out = run(loss, make_batch(batch=4096))
    u = 10.0 + torch.randn(1_000_000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    log_one_minus_tanh2 = 2 * (math.log(2.0) - u - torch.nn.functional.softplus(-2 * u))
    expected = ACTION_DIM * (0.5 * math.log(2 * math.pi * math.e) + log_one_minus_tanh2.mean().item())
    assert expected < -30  # ~ -17.2 per dimension
    assert out["entropy"].item() == pytest.approx(expected, abs=0.5)
    assert out["loss_actor"].item() == pytest.approx(-expected, abs=0.5)  # alpha = 1, constant critics at 0
    out["loss_actor"].backward()
    scale_grad = loss.actor_network_params.get(("module", "0", "module", "scale")).grad
    assert scale_grad is not None and scale_grad.item() < 0


@pytest.mark.parametrize("psi, beta", [(1.0, 1.0), (0.5, 0.0), (2.0, 3.0)])
def test_actor_and_alpha_losses(psi, beta):
    alpha = 2.0
    loss = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(0.0)), psi=psi, intervention_weight=beta,
                     alpha_init=alpha, target_entropy=-1.5)
    set_online(loss.qvalue_network_params, "value", [4.0, 3.0])
    set_online(loss.intervention_qvalue_network_params, "value", [0.5, 0.25])
    out = run(loss, make_batch())
    # alpha * mean(log pi) - psi * min_k Q_k + beta * min_k Q_int_k
    assert out["loss_actor"].item() == pytest.approx(-alpha * out["entropy"].item() - psi * 3.0 + beta * 0.25, rel=1e-5)
    # -log_alpha * mean(log pi + target_entropy)
    assert out["loss_alpha"].item() == pytest.approx(-math.log(alpha) * (-out["entropy"].item() - 1.5), rel=1e-5)
    assert out["alpha"].item() == pytest.approx(alpha)


@pytest.mark.parametrize("cosine_cost", [True, False])
def test_intervention_target_is_the_cost_at_terminal_steps(cosine_cost):
    start = (torch.arange(BATCH) % 3 == 0).unsqueeze(-1)
    batch = make_batch(intervention=1.0, start=start, terminated=1.0)
    # a stored cost on every takeover row: only the start of a takeover is charged
    batch["next", "intervention_cost"] = torch.rand(BATCH, 1, generator=torch.Generator().manual_seed(2)) + 0.1
    loss = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(9.0)), cosine_cost=cosine_cost)
    set_online(loss.intervention_qvalue_network_params, "value", [0.2, 0.6])
    out = run(loss, batch)
    start_f = start.squeeze(-1).float()
    cost = batch["next", "intervention_cost"].squeeze(-1) * start_f if cosine_cost else start_f
    expected = 0.5 * sum(((d - cost) ** 2).mean() for d in (0.2, 0.6))
    assert out["loss_intervention_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)
    assert out["q_intervention"] == pytest.approx(0.4)


def test_intervention_target_bootstraps_without_entropy():
    start = (torch.arange(BATCH) % 3 == 0).unsqueeze(-1)
    terminated = (torch.arange(BATCH) % 2 == 0).unsqueeze(-1)
    batch = make_batch(intervention=1.0, start=start, terminated=terminated)
    gamma = 0.8
    loss = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(2.0)), gamma=gamma)
    set_online(loss.intervention_qvalue_network_params, "value", [1.0, 3.0])
    out = run(loss, batch)
    target = (batch["next", "intervention_cost"].squeeze(-1) * start.squeeze(-1)
              + gamma * 2.0 * (~terminated.squeeze(-1)).float())
    expected = 0.5 * sum(((d - target) ** 2).mean() for d in (1.0, 3.0))
    assert out["loss_intervention_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)


def test_cosine_cost_flag_decides_whether_the_stored_cost_matters():
    batch = make_batch(intervention=0.5)
    other = batch.clone()
    other["next", "intervention_cost"] = other["next", "intervention_cost"] * 0.25 + 0.5 * other[
        "next", "intervention_start"].float()
    constant = make_loss(cosine_cost=False)
    assert torch.equal(run(constant, batch)["loss_intervention_qvalue"],
                       run(constant, other)["loss_intervention_qvalue"])
    cosine = make_loss(cosine_cost=True)
    assert not torch.equal(run(cosine, batch)["loss_intervention_qvalue"],
                           run(cosine, other)["loss_intervention_qvalue"])


def test_intervention_critic_reads_the_agents_action_not_the_executed_one():
    """The paper's equation: Q_int(s, a_AV)."""
    loss = make_loss()
    batch = make_batch(intervention=0.5)
    base = run(loss, batch)["loss_intervention_qvalue"]
    for key, should_change in ((("action",), True), (("next", "behavior_action"), False)):
        other = batch.clone()
        other[key] = -other[key]
        changed = not torch.equal(run(loss, other)["loss_intervention_qvalue"], base)
        assert changed == should_change, key


def test_multi_dimensional_batch_matches_the_flat_batch():
    loss = make_loss()
    flat = run(loss, make_batch(batch=24))
    nested = run(loss, make_batch(batch=24, shape=(4, 6)))
    for key in LOSS_KEYS + DIAGNOSTIC_KEYS:
        torch.testing.assert_close(nested[key], flat[key], msg=key)


# --------------------------------------------------------------------------- arguments


@pytest.mark.parametrize("kwargs, field", [
    ({"gamma": 1.5}, "gamma"),
    ({"gamma": -0.1}, "gamma"),
    ({"gap_coef": -1.0}, "gap_coef"),
    ({"psi": math.nan}, "psi"),
    ({"intervention_weight": math.inf}, "intervention_weight"),
    ({"alpha_init": 0.0}, "alpha_init"),
    ({"alpha_init": -1.0}, "alpha_init"),
    ({"num_qvalue_nets": 0}, "num_qvalue_nets"),
    ({"target_entropy": "high"}, "target_entropy"),
    ({"target_entropy": math.nan}, "target_entropy"),
])
def test_invalid_arguments_raise_value_error_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        make_loss(**kwargs)


def test_target_entropy_auto_and_explicit():
    assert make_loss().target_entropy.item() == -ACTION_DIM
    assert make_loss(target_entropy=2.0).target_entropy.item() == 2.0


# --------------------------------------------------------------------------- target networks


def test_soft_update_moves_targets_towards_online_params():
    loss = make_loss()
    updater = SoftUpdate(loss, tau=0.005)
    for name in ("qvalue_network_params", "intervention_qvalue_network_params"):
        online = getattr(loss, name)
        with torch.no_grad():
            for p in online.values(True, True):
                p.add_(1.0)
    before = {n: (getattr(loss, "target_" + n).clone(), getattr(loss, n).detach().clone())
              for n in ("qvalue_network_params", "intervention_qvalue_network_params")}
    updater.step()
    for name, (target, online) in before.items():
        new_target = getattr(loss, "target_" + name)
        for key, t in target.items(True, True):
            expected = 0.995 * t + 0.005 * online[key]
            torch.testing.assert_close(new_target[key], expected)
            assert (new_target[key] - online[key]).abs().sum() < (t - online[key]).abs().sum(), (name, key)
    # and the loss reads the updated targets: constant critics make this visible in td_loss
    const = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(0.0)), alpha_init=1e-9, fixed_alpha=True, gamma=1.0)
    updater = SoftUpdate(const, tau=0.5)
    set_online(const.qvalue_network_params, "value", [4.0, 4.0])
    updater.step()  # targets: 0 -> 2
    out = run(const, make_batch(terminated=0.0))
    assert out["td_loss"] == pytest.approx(0.5 * 2 * (4.0 - 2.0) ** 2, rel=1e-5)


# --------------------------------------------------------------------------- learning


def test_actor_learns_to_steer_to_the_mentors_side(one_thread):
    """The mentor corrects every left-steering proposal to (+0.7, the agent's throttle).

    After a couple of hundred updates the actor's deterministic steering is positive and the
    proxy-Q prefers the mentor's action to the initially corrected agent actions."""
    torch.manual_seed(0)
    hidden = (64, 64)
    loss = PERLHFLoss(make_actor(OBS_DIM, ACTION_DIM, hidden), make_qvalue(OBS_DIM, ACTION_DIM, hidden),
                      make_qvalue(OBS_DIM, ACTION_DIM, hidden))
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
    updater = SoftUpdate(loss, tau=0.005)
    test_obs = torch.randn(512, OBS_DIM)
    initial = actor_action(loss, test_obs, ExplorationType.RANDOM)
    bad = initial[:, 0] < 0  # the proposals the mentor corrected at the start
    assert 0.2 < bad.float().mean() < 0.8
    batch_size = 128
    for _ in range(200):
        obs = torch.randn(batch_size, OBS_DIM)
        agent = actor_action(loss, obs, ExplorationType.RANDOM)
        takeover = agent[:, :1] < 0
        behavior = torch.where(takeover, torch.stack([torch.full_like(agent[:, 0], 0.7), agent[:, 1]], -1), agent)
        cost = (1 - torch.nn.functional.cosine_similarity(agent, behavior, dim=-1)).unsqueeze(-1) * takeover
        no = torch.zeros(batch_size, 1, dtype=torch.bool)
        batch = TensorDict({
            "observation": obs, "action": agent,
            "next": {"observation": torch.randn(batch_size, OBS_DIM), "behavior_action": behavior,
                     "intervention": takeover, "intervention_start": takeover, "intervention_cost": cost,
                     "reward": torch.zeros(batch_size, 1), "done": no, "terminated": no}}, [batch_size])
        out = loss(batch)
        optim.zero_grad()
        sum(out[k] for k in LOSS_KEYS).backward()
        optim.step()
        updater.step()
    final = actor_action(loss, test_obs)
    assert final[:, 0].mean() > 0.3, final[:, 0].mean()
    obs = test_obs[bad]
    mentor = torch.stack([torch.full_like(initial[bad, 0], 0.7), initial[bad, 1]], -1)
    q_mentor, q_agent = q_values(loss, obs, mentor).min(0)[0], q_values(loss, obs, initial[bad]).min(0)[0]
    assert q_mentor.mean() > q_agent.mean()
    assert (q_mentor > q_agent).float().mean() > 0.9


def test_default_is_the_papers_single_intervention_critic():
    torch.manual_seed(0)
    loss = PERLHFLoss(make_actor(OBS_DIM, ACTION_DIM, HIDDEN), critic(ConstantQ(0.0)), critic(ConstantQ(0.0)))
    assert loss.intervention_qvalue_network_params.get(("module", "value")).shape[0] == 1
    assert loss.qvalue_network_params.get(("module", "value")).shape[0] == 2  # the proxy Q stays a twin
    set_online(loss.intervention_qvalue_network_params, "value", [0.7])
    out = run(loss, make_batch())
    assert out["q_intervention"] == pytest.approx(0.7)
    assert out["loss_actor"].item() == pytest.approx(-1.0 * out["entropy"].item() - 0.0 + 0.7, rel=1e-5)


# --------------------------------------------------------------------------- HAIM-DRL's disturbance critic

DISTURBANCE_KEYS = ("loss_disturbance_qvalue", "q_disturbance")

# make_loss(**kwargs) on make_batch(terminated=0.25), run(...) with seed 123, recorded from PERLHFLoss before
# the disturbance option existed (commit 30efda3; the same on 1 and 2 threads).
PREVIOUS_OUTPUTS = {
    "twin intervention critic": ({}, {
        "loss_qvalue": 1.0557410717010498, "loss_intervention_qvalue": 0.6804097890853882,
        "loss_actor": -1.465947151184082, "loss_alpha": -0.0, "alpha": 1.0, "entropy": 1.1275405883789062,
        "td_loss": 1.1043307781219482, "gap_loss": -0.04858972877264023, "q_behavior": 0.36768314242362976,
        "q_agent": 0.36252516508102417, "q_intervention": 0.013107817620038986, "intervention_rate": 0.46875}),
}


def with_disturbance(batch: TensorDict, cost=None, seed: int = 4) -> TensorDict:
    """``batch`` with a ``("next", "disturbance_cost")`` (random in [0, 1) on a third of the rows by default)."""
    g = torch.Generator().manual_seed(seed)
    if cost is None:
        cost = torch.rand(*batch.shape, 1, generator=g) * (torch.rand(*batch.shape, 1, generator=g) < 1 / 3)
    batch = batch.clone()
    batch["next", "disturbance_cost"] = cost.expand(*batch.shape, 1).clone()
    return batch


def disturbance_loss(disturbance_qvalue=None, seed: int = 0, **kwargs) -> PERLHFLoss:
    """``make_loss`` plus a disturbance critic built after the other networks (same ``seed``)."""
    torch.manual_seed(seed)
    actor = make_actor(OBS_DIM, ACTION_DIM, HIDDEN)
    qvalue, intervention_qvalue = make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN), make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN)
    disturbance_qvalue = disturbance_qvalue if disturbance_qvalue is not None else make_qvalue(OBS_DIM, ACTION_DIM,
                                                                                              HIDDEN)
    kwargs.setdefault("num_intervention_qvalue_nets", 2)
    kwargs.setdefault("failure_target", "zero")
    return PERLHFLoss(actor, qvalue, intervention_qvalue, disturbance_qvalue, **kwargs)


@pytest.mark.parametrize("case", sorted(PREVIOUS_OUTPUTS))
def test_without_a_disturbance_critic_the_outputs_are_the_previous_numbers(case):
    kwargs, previous = PREVIOUS_OUTPUTS[case]
    loss = make_loss(**kwargs)
    assert not loss.has_disturbance_critic
    assert not any("disturbance" in name for name, _ in loss.named_parameters())
    # the key is ignored when there is no disturbance critic
    for batch in (make_batch(terminated=0.25), with_disturbance(make_batch(terminated=0.25))):
        out = run(loss, batch)
        assert set(out.keys()) - set(previous) == {"failure_rate", "q_failure"}  # diagnostics added since
        for key, value in previous.items():
            assert out[key].item() == pytest.approx(value, rel=1e-6, abs=1e-7), key


def test_the_disturbance_critic_changes_nothing_but_the_actor_term():
    """Same networks and seeds with and without the option: every other output is bit-identical, and the
    actor loss gains exactly ``disturbance_weight * min_k Q_dist_k``."""
    batch = with_disturbance(make_batch(terminated=0.25))
    off = make_loss(seed=0)
    on = disturbance_loss(critic(ConstantQ(0.0)), seed=0, disturbance_weight=2.5)
    set_online(on.disturbance_qvalue_network_params, "value", [0.4, 0.3])
    a, b = run(off, batch), run(on, batch)
    assert set(b.keys()) == set(a.keys()) | set(DISTURBANCE_KEYS)
    for key in a.keys():  # noqa: SIM118 (iterating a TensorDict walks its batch dim, not its keys)
        if key != "loss_actor":
            assert torch.equal(a[key], b[key]), key
    assert b["loss_actor"].item() == pytest.approx(a["loss_actor"].item() + 2.5 * 0.3, rel=1e-6)
    assert b["q_disturbance"] == pytest.approx(0.35)


def test_disturbance_outputs_and_gradient_routing():
    loss = disturbance_loss()
    groups = set(PARAM_GROUPS) | {"disturbance_qvalue_network_params"}
    assert {name.split(".")[0] for name, _ in loss.named_parameters()} == groups
    assert loss.disturbance_qvalue_network_params.get(("module", "mlp", "0", "weight")).shape[0] == 2  # a twin
    batch = with_disturbance(make_batch())
    for key, group in (("loss_disturbance_qvalue", "disturbance_qvalue_network_params"),
                       ("loss_actor", "actor_network_params"), ("loss_qvalue", "qvalue_network_params")):
        for p in loss.parameters():
            p.grad = None
        out = run(loss, batch)
        assert out[key].requires_grad and not out["q_disturbance"].requires_grad
        out[key].backward()
        got = grad_groups(loss)
        assert all(got[group]), key
        assert not any(any(got[other]) for other in groups - {group}), f"{key} leaked a gradient"


def test_disturbance_target_is_the_cost_plus_the_discounted_target_critic():
    start = (torch.arange(BATCH) % 3 == 0).unsqueeze(-1)
    terminated = (torch.arange(BATCH) % 2 == 0).unsqueeze(-1)
    cost = torch.rand(BATCH, 1, generator=torch.Generator().manual_seed(7))
    batch = with_disturbance(make_batch(intervention=start, terminated=terminated), cost)
    gamma = 0.8
    loss = disturbance_loss(critic(ConstantQ(2.0)), gamma=gamma)  # targets stay at 2
    set_online(loss.disturbance_qvalue_network_params, "value", [1.0, 3.0])
    out = run(loss, batch)
    target = cost.squeeze(-1) + gamma * 2.0 * (~terminated.squeeze(-1)).float()
    expected = 0.5 * sum(((d - target) ** 2).mean() for d in (1.0, 3.0))
    assert out["loss_disturbance_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)


def test_disturbance_critic_is_trained_on_the_executed_action():
    loss = disturbance_loss()
    batch = with_disturbance(make_batch(intervention=0.5))
    base = run(loss, batch)["loss_disturbance_qvalue"]
    for key, should_change in ((("next", "behavior_action"), True), ("action", False)):
        other = batch.clone()
        other[key] = -other[key]
        assert (not torch.equal(run(loss, other)["loss_disturbance_qvalue"], base)) == should_change, key


@pytest.mark.parametrize("kwargs, field", [({"disturbance_weight": -1.0}, "disturbance_weight"),
                                           ({"disturbance_weight": math.nan}, "disturbance_weight"),
                                           ({"num_disturbance_qvalue_nets": 0}, "num_disturbance_qvalue_nets")])
def test_invalid_disturbance_arguments_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        disturbance_loss(**kwargs)


def test_soft_update_reaches_the_disturbance_targets():
    loss = disturbance_loss(critic(ConstantQ(0.0)))
    updater = SoftUpdate(loss, tau=0.5)
    set_online(loss.disturbance_qvalue_network_params, "value", [4.0, 2.0])
    updater.step()
    torch.testing.assert_close(loss.target_disturbance_qvalue_network_params.get(("module", "value")),
                               torch.tensor([2.0, 1.0]))


def test_disturbance_critic_converges_to_the_discounted_cost_of_a_chain(one_thread):
    """A deterministic chain s_0 -> ... -> s_4 (terminal), one-hot states, costs c = (0, .5, 0, 1, 0) whatever
    the action: ``Q_dist(s_i, a)`` must reach ``V_i = sum_j gamma^(j-i) c_j``."""
    n, gamma = 5, 0.9
    costs = torch.tensor([0.0, 0.5, 0.0, 1.0, 0.0])
    values = torch.zeros(n)
    for i in reversed(range(n)):
        values[i] = costs[i] + (gamma * values[i + 1] if i + 1 < n else 0.0)
    eye = torch.eye(n)  # the chain's observations
    torch.manual_seed(0)
    hidden = (64, 64)
    loss = PERLHFLoss(make_actor(n, ACTION_DIM, hidden), make_qvalue(n, ACTION_DIM, hidden),
                      make_qvalue(n, ACTION_DIM, hidden), make_qvalue(n, ACTION_DIM, hidden), gamma=gamma)
    optim = torch.optim.Adam(loss.disturbance_qvalue_network_params.flatten_keys().values(), lr=3e-3)
    updater = SoftUpdate(loss, tau=0.05)
    reps = 16
    states = eye.repeat(reps, 1)
    next_states = torch.cat([eye[1:], eye[:1]]).repeat(reps, 1)  # s_4's successor is unused: terminal
    terminated = (torch.arange(n) == n - 1).repeat(reps).unsqueeze(-1)
    no = torch.zeros(n * reps, 1, dtype=torch.bool)
    for _ in range(300):  # measured: max error 0.009 after 300 updates, 0.004 after 600
        actions = torch.rand(n * reps, ACTION_DIM) * 2 - 1
        batch = make_transitions(states, next_states, actions, actions, no, no, terminated,
                                 disturbance_cost=costs.repeat(reps).unsqueeze(-1))
        out = loss(batch)
        optim.zero_grad()
        out["loss_disturbance_qvalue"].backward()
        optim.step()
        updater.step()
    test_actions = torch.rand(n, 32, ACTION_DIM) * 2 - 1
    with torch.no_grad():
        learned = loss._q("q_dist", loss.disturbance_qvalue_network_params,
                          TensorDict({"observation": eye.unsqueeze(1).expand(n, 32, n)}, [n, 32]),
                          test_actions).min(0)[0].mean(-1)
    torch.testing.assert_close(learned, values, atol=0.03, rtol=0.0)


def test_actor_moves_away_from_actions_the_disturbance_critic_charges(one_thread):
    """``Q_dist(s, a) = 2 * max(-a[1], 0)`` (braking is charged), proxy Q and Q_int constant: with a
    disturbance weight the policy stops proposing braking; without one it keeps its spread."""

    class BrakingCost(nn.Module):
        def forward(self, observation, action):
            return 2.0 * (-action[..., 1:]).clamp(min=0)

    obs = torch.randn(256, OBS_DIM, generator=torch.Generator().manual_seed(3))

    def braking_share(loss: PERLHFLoss) -> float:
        torch.manual_seed(9)
        return (actor_action(loss, obs.repeat(8, 1), ExplorationType.RANDOM)[:, 1] < 0).float().mean().item()

    def train_actor(weight: float) -> tuple[float, float]:
        torch.manual_seed(2)
        loss = PERLHFLoss(make_actor(OBS_DIM, ACTION_DIM, HIDDEN), critic(ConstantQ(0.0)), critic(ConstantQ(0.0)),
                          critic(BrakingCost()), disturbance_weight=weight, alpha_init=0.05, fixed_alpha=True)
        optim = torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=3e-3)
        before = braking_share(loss)
        for _ in range(100):
            batch = with_disturbance(make_batch(batch=256, seed=5), torch.zeros(256, 1))
            batch["observation"] = obs
            out = loss(batch)
            optim.zero_grad()
            out["loss_actor"].backward()
            optim.step()
        return before, braking_share(loss)

    before, charged = train_actor(1.0)
    _, free = train_actor(0.0)
    assert 0.3 < before < 0.7, before
    assert charged < 0.1, (before, charged)
    assert free > 0.3, free


# --------------------------------------------------------------------------- failure terminations


def with_outcomes(batch: TensorDict, outcome: list[str]) -> TensorDict:
    """``outcome`` per row: ``"go"`` (not terminal), ``"success"`` or ``"failure"`` (terminal without success)."""
    terminated = torch.tensor([o != "go" for o in outcome]).unsqueeze(-1)
    batch["next", "terminated"] = terminated
    batch["next", "done"] = terminated.clone()
    batch["next", "success"] = torch.tensor([o == "success" for o in outcome]).unsqueeze(-1)
    return batch


@pytest.mark.parametrize("failure_target, failure_y", [("zero", 0.0), ("bootstrap", -4.5), ("batch_min", -4.5)])
def test_failure_rows_take_the_chosen_target_and_successes_stay_terminal(failure_target, failure_y):
    outcome = ["go", "success", "failure", "go"] * (BATCH // 4)
    batch = with_outcomes(make_batch(intervention=0.0), outcome)
    gamma = 0.9  # alpha ~ 0: a non-terminal row's target is gamma * (-5) = -4.5
    loss = make_loss(critic(ConstantQ(-5.0)), critic(ConstantQ(0.0)), gamma=gamma, alpha_init=1e-9,
                     fixed_alpha=True, failure_target=failure_target)
    set_online(loss.qvalue_network_params, "value", [1.0, -3.0])
    out = run(loss, batch)
    y = torch.tensor([{"go": -4.5, "success": 0.0, "failure": failure_y}[o] for o in outcome])
    expected = 0.5 * sum(((c - y) ** 2).mean() for c in (1.0, -3.0))
    assert out["td_loss"].item() == pytest.approx(expected.item(), rel=1e-5)
    assert out["failure_rate"].item() == pytest.approx(0.25)
    assert out["q_failure"].item() == pytest.approx(-1.0)  # mean over the copies (1, -3) at failure rows


def test_without_a_success_key_every_terminal_row_is_a_failure():
    batch = make_batch(terminated=(torch.arange(BATCH) % 2 == 0).unsqueeze(-1))
    assert ("next", "success") not in batch.keys(True)
    out = run(make_loss(), batch)
    assert out["failure_rate"].item() == pytest.approx(0.5)


def test_the_zero_failure_target_is_the_previous_loss():
    batch = with_outcomes(make_batch(), ["go", "success", "failure", "go"] * (BATCH // 4))
    a, b = run(make_loss(), batch), run(make_loss(failure_target="zero"), batch)
    for key in LOSS_KEYS:
        assert torch.equal(a[key], b[key]), key


def test_invalid_failure_target_names_the_field():
    with pytest.raises(ValueError, match="failure_target"):
        make_loss(failure_target="pessimistic")


def test_a_crash_is_worth_more_than_driving_on_unless_failures_are_pinned_low(one_thread):
    """A tiny chain without reward. From s0 action (+1, .) crashes (terminal failure) and (-1, .) drives on
    to s1, which drives on for ever. The actor is a narrow fixed Gaussian (log pi > 0), so driving on is
    worth ``-alpha * E[log pi] * gamma / (1 - gamma) < 0``. With the terminal target 0 the critic ranks the
    crash above driving on; with ``batch_min`` the crash is worth no more than driving on."""
    obs_dim, gamma, alpha = 3, 0.8, 0.5  # driving on: -0.8 * 0.5 * 1.78 / 0.2 = -3.6
    s0, s1, crashed = torch.eye(obs_dim)
    crash, drive = torch.tensor([1.0, 0.0]), torch.tensor([-1.0, 0.0])

    def fitted(failure_target: str) -> tuple[float, float]:
        torch.manual_seed(0)
        module = TensorDictModule(FixedGaussian(0.0, 0.1), in_keys=["observation"], out_keys=["loc", "scale"])
        from torchrl.data import Bounded
        from torchrl.modules import ProbabilisticActor, TanhNormal

        actor = ProbabilisticActor(module, in_keys=["loc", "scale"], spec=Bounded(-1.0, 1.0, (ACTION_DIM,)),
                                   distribution_class=TanhNormal, distribution_kwargs={"low": -1.0, "high": 1.0})
        loss = PERLHFLoss(actor, make_qvalue(obs_dim, ACTION_DIM, (64, 64)), make_qvalue(obs_dim, ACTION_DIM, (8,)),
                          gamma=gamma, alpha_init=alpha, fixed_alpha=True, action_dim=ACTION_DIM,
                          failure_target=failure_target)
        optim = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=3e-3)
        updater = SoftUpdate(loss, tau=0.2)
        reps = 32
        obs = torch.stack([s0, s0, s1]).repeat(reps, 1)
        nxt = torch.stack([crashed, s1, s1]).repeat(reps, 1)
        actions = torch.stack([crash, drive, drive]).repeat(reps, 1)
        no = torch.zeros(3 * reps, 1, dtype=torch.bool)
        batch = with_outcomes(make_transitions(obs, nxt, actions, actions, no, no, no),
                              ["failure", "go", "go"] * reps)
        for _ in range(300):
            out = loss(batch)
            optim.zero_grad()
            out["loss_qvalue"].backward()
            optim.step()
            updater.step()
        q = q_values(loss, torch.stack([s0, s0]), torch.stack([crash, drive])).mean(0)
        return q[0].item(), q[1].item()

    crash_zero, drive_zero = fitted("zero")
    assert drive_zero < -1.0 and crash_zero == pytest.approx(0.0, abs=0.3)  # measured: -1.7 and -0.01
    assert crash_zero > drive_zero + 1.0  # the defect: a crash beats driving on
    crash_min, drive_min = fitted("batch_min")
    assert crash_min <= drive_min + 0.3  # measured: -3.0 against -2.7


def test_the_default_failure_target_is_the_recipes():
    """One default per fact: the component's default is what the PE-RLHF recipe runs."""
    from pe_rlhf.algorithms.proxy_q.config_schema import default

    loss = PERLHFLoss(make_actor(OBS_DIM, ACTION_DIM, HIDDEN), make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN),
                      make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN))
    assert loss.failure_target == default("loss.failure_target") == "batch_min"
