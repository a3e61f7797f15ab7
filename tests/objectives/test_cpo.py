"""Tests of CPO: the conjugate-gradient solver, the dual step against a brute-force solution of the same
quadratic-constrained problem, and full policy updates of a TanhNormal actor on synthetic batches (feasible
with a binding constraint, infeasible -> recovery, line-search backtracking, rejection).

The policy checks recompute ``b`` (the cost surrogate's gradient) and the KL independently of
``CPOLoss.policy_step`` and compare them with the parameter change it made.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torch.distributions import Normal, kl_divergence
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

from pe_rlhf.objectives.cpo import CPO_CASES, CPOLoss, conjugate_gradient, cpo_direction

pytestmark = pytest.mark.usefixtures("one_thread_module")

OBS, ACT, BATCH, TARGET_KL = 3, 2, 256, 0.01


# --------------------------------------------------------------------------- helpers

def make_loss(seed: int = 0, distribution_class=TanhNormal, **kwargs) -> CPOLoss:
    torch.manual_seed(seed)
    net = nn.Sequential(MLP(in_features=OBS, out_features=2 * ACT, num_cells=[16]), NormalParamExtractor())
    actor = ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"],
                               distribution_class=distribution_class)
    critic = TensorDictModule(MLP(in_features=OBS, out_features=1, num_cells=[16]), ["observation"], ["state_value"])
    cost_critic = TensorDictModule(MLP(in_features=OBS, out_features=1, num_cells=[16]), ["observation"],
                                   ["state_cost_value"])
    kwargs.setdefault("target_kl", TARGET_KL)
    return CPOLoss(actor, critic, cost_critic, **kwargs)


def make_batch(loss: CPOLoss, seed: int = 1) -> TensorDict:
    """Actions from the policy; the reward grows with ``a_0``, the cost with ``a_0 + a_1``: they conflict."""
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({"observation": torch.randn(BATCH, OBS, generator=g)}, [BATCH])
    torch.manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM), \
            loss.actor_network_params.to_module(loss.actor_network):
        loss.actor_network(td)
    action = td["action"]
    td["advantage"] = action[:, :1] - action[:, :1].mean()
    td["cost_advantage"] = (action[:, :1] + action[:, 1:]) - (action[:, :1] + action[:, 1:]).mean()
    return td


def actor_vector(loss: CPOLoss) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1).clone() for p in loss._actor_params()])


def cost_gradient(loss: CPOLoss, td: TensorDict) -> torch.Tensor:
    """``b = grad mean(ratio * A_c)`` at the current parameters (ratio = 1 there)."""
    _, log_prob = loss.policy(td)
    surrogate = ((log_prob - log_prob.detach()).exp() * td["cost_advantage"].squeeze(-1)).mean()
    return torch.cat([g.reshape(-1) for g in torch.autograd.grad(surrogate, loss._actor_params())])


def policy_stats(loss: CPOLoss, td: TensorDict, old_normal: Normal, old_log_prob: torch.Tensor):
    """Mean KL(old || current) and the cost surrogate ``mean(ratio * A_c)`` at the current parameters."""
    with torch.no_grad():
        normal, log_prob = loss.policy(td)
        kl = kl_divergence(old_normal, normal).sum(-1).mean().item()
        cost = ((log_prob - old_log_prob).exp() * td["cost_advantage"].squeeze(-1)).mean().item()
    return kl, cost


def old_policy(loss: CPOLoss, td: TensorDict):
    with torch.no_grad():
        normal, log_prob = loss.policy(td)
    return Normal(normal.loc.clone(), normal.scale.clone()), log_prob.clone()


# --------------------------------------------------------------------------- the solvers

@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_conjugate_gradient_solves_a_small_spd_system(dtype):
    g = torch.Generator().manual_seed(0)
    m = torch.randn(6, 6, generator=g, dtype=torch.float64)
    matrix = (m @ m.T + 6 * torch.eye(6, dtype=torch.float64)).to(dtype)  # condition number ~ 5
    rhs = torch.randn(6, generator=g, dtype=torch.float64).to(dtype)
    x = conjugate_gradient(lambda v: matrix @ v, rhs, iterations=20, residual_tol=1e-14)
    expected = torch.linalg.solve(matrix.double(), rhs.double())
    assert (x.double() - expected).abs().max() < 1e-6
    assert (matrix.double() @ x.double() - rhs.double()).abs().max() < 1e-5


def brute_force(g, b, hessian, c, delta, points=200_000):
    """Max of ``g^T x`` over ``{c + b^T x <= 0, x^T H x / 2 <= delta}`` in 2-D: the optimum of a linear objective
    lies on the ellipse or on the chord the half-plane cuts from it; both are sampled densely."""
    chol = torch.linalg.cholesky(hessian)
    radius = math.sqrt(2 * delta)
    angles = torch.linspace(0, 2 * math.pi, points, dtype=torch.float64)
    circle = radius * torch.stack([angles.cos(), angles.sin()], -1)
    b_y = torch.linalg.solve_triangular(chol, b.unsqueeze(-1), upper=False).squeeze(-1)  # y = L^T x: b^T x = b_y^T y
    normal = b_y / b_y.norm()
    foot = -c / b_y.norm() * normal  # closest point of the line b_y^T y = -c
    half = math.sqrt(max(radius ** 2 - foot.norm().item() ** 2, 0.0))
    tangent = torch.stack([-normal[1], normal[0]])
    chord = foot + torch.linspace(-half, half, points, dtype=torch.float64).unsqueeze(-1) * tangent
    y = torch.cat([circle, chord])
    x = torch.linalg.solve_triangular(chol.T, y.unsqueeze(-1), upper=True).squeeze(-1)
    feasible = (c + x @ b <= 1e-9) & (0.5 * ((x @ hessian) * x).sum(-1) <= delta * (1 + 1e-9))
    if not feasible.any():
        return None
    return (x[feasible] @ g).max().item()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("c", [-0.3, -0.02, 0.0, 0.02, 0.3])
def test_dual_step_matches_the_brute_force_optimum(seed, c):
    gen = torch.Generator().manual_seed(seed)
    m = torch.randn(2, 2, generator=gen, dtype=torch.float64)
    hessian = m @ m.T + 0.5 * torch.eye(2, dtype=torch.float64)
    g, b = torch.randn(2, generator=gen, dtype=torch.float64), torch.randn(2, generator=gen, dtype=torch.float64)
    g_dir, b_dir = torch.linalg.solve(hessian, g), torch.linalg.solve(hessian, b)
    direction = cpo_direction(g_dir, b_dir, (g @ g_dir).item(), (b @ g_dir).item(), (b @ b_dir).item(), c, TARGET_KL)
    x = direction.step
    best = brute_force(g, b, hessian, c, TARGET_KL)
    assert 0.5 * x @ hessian @ x <= TARGET_KL * (1 + 1e-6)
    if best is None:  # infeasible: the recovery step, straight down the cost gradient to the region's edge
        assert CPO_CASES[direction.case] == "recovery"
        torch.testing.assert_close(x, -math.sqrt(2 * TARGET_KL / (b @ b_dir)) * b_dir)
    else:
        assert CPO_CASES[direction.case] != "recovery"
        assert c + b @ x <= 1e-9
        assert (g @ x).item() == pytest.approx(best, abs=1e-6 + 1e-4 * abs(best))


# --------------------------------------------------------------------------- policy updates

@pytest.mark.parametrize("distribution_class", [TanhNormal, Normal])  # Normal: per-dimension log-probs
def test_feasible_step_keeps_the_linearised_constraint_and_the_kl_bound(distribution_class):
    loss = make_loss(distribution_class=distribution_class)
    td = make_batch(loss)
    theta_old, b = actor_vector(loss), cost_gradient(loss, td)
    old_normal, old_log_prob = old_policy(loss, td)
    info = loss.policy_step(td, mean_episode_cost=0.99)  # c = -0.01: feasible, the constraint binds
    assert CPO_CASES[int(info["case"])] == "feasible_start" and info["lagrange_cost"] > 0
    assert info["step_fraction"] > 0
    x = actor_vector(loss) - theta_old
    assert x.norm() > 0
    assert -0.01 + (b @ x).item() <= 1e-5
    kl, _ = policy_stats(loss, td, old_normal, old_log_prob)
    assert kl <= TARGET_KL and kl == pytest.approx(info["kl"].item(), rel=1e-4)
    assert info["surrogate_reward_gain"] > 0


def test_constraint_inactive_far_from_the_limit_is_a_trust_region_step():
    loss = make_loss()
    td = make_batch(loss)
    theta_old, b = actor_vector(loss), cost_gradient(loss, td)
    info = loss.policy_step(td, mean_episode_cost=-100.0)  # far below the limit: plain TRPO
    assert CPO_CASES[int(info["case"])] == "constraint_inactive" and info["lagrange_cost"] == 0
    assert info["step_fraction"] > 0 and info["surrogate_reward_gain"] > 0 and info["kl"] <= TARGET_KL
    assert (b @ (actor_vector(loss) - theta_old)).item() > 0  # the reward step alone raises the cost here


def test_infeasible_start_takes_a_recovery_step_that_decreases_the_cost_surrogate():
    loss = make_loss()
    td = make_batch(loss)
    old_normal, old_log_prob = old_policy(loss, td)
    _, cost_before = policy_stats(loss, td, old_normal, old_log_prob)
    info = loss.policy_step(td, mean_episode_cost=50.0)  # c = 49: out of reach of one trust-region step
    assert CPO_CASES[int(info["case"])] == "recovery" and info["step_fraction"] > 0
    kl, cost_after = policy_stats(loss, td, old_normal, old_log_prob)
    assert cost_after < cost_before - 1e-3
    assert info["surrogate_cost_change"] == pytest.approx(cost_after - cost_before, abs=1e-6)
    assert kl <= TARGET_KL


def test_line_search_backtracks_when_the_full_step_breaks_a_tiny_kl_bound():
    loss = make_loss(target_kl=1e-5, max_backtracks=40)
    td = make_batch(loss)
    theta_old = actor_vector(loss)
    old = old_policy(loss, td)
    # a trust-region step sized for KL 0.01: its KL is ~1000x the bound the line search checks
    g = torch.cat([gr.reshape(-1) for gr in torch.autograd.grad(
        ((loss.policy(td)[1] - old[1]).exp() * td["advantage"].squeeze(-1)).mean(), loss._actor_params())])
    step = 0.05 * g / g.norm()
    loss._set_actor_params(loss._actor_params(), theta_old + step)
    full_kl, _ = policy_stats(loss, td, *old)
    loss._set_actor_params(loss._actor_params(), theta_old)
    assert full_kl > 1e-5

    fraction, stats = loss.line_search(td, old, step, constraint_violation=-100.0)
    assert 0 < fraction < 1 and stats["kl"] <= 1e-5
    torch.testing.assert_close(actor_vector(loss), theta_old + fraction * step)
    loss._set_actor_params(loss._actor_params(), theta_old + fraction / loss.backtrack_ratio * step)
    assert policy_stats(loss, td, *old)[0] > 1e-5  # the previous, longer step was rejected for its KL


def test_line_search_restores_the_policy_when_no_step_is_acceptable():
    """Infeasible (``c > 0``) and a step along ``+b``: every fraction raises the cost surrogate, none is kept."""
    loss = make_loss(max_backtracks=5)
    td = make_batch(loss)
    theta_old, b = actor_vector(loss), cost_gradient(loss, td)
    fraction, stats = loss.line_search(td, old_policy(loss, td), 1e-3 * b / b.norm(), constraint_violation=1.0)
    assert fraction == 0 and stats["surrogate_cost_change"] == 0
    assert torch.equal(actor_vector(loss), theta_old)


# --------------------------------------------------------------------------- value losses

def test_value_losses_are_mse_to_the_gae_targets_and_train_only_the_critics():
    loss = make_loss()
    loss.make_value_estimator(gamma=0.5, lmbda=1.0)
    time = 4
    g = torch.Generator().manual_seed(3)
    td = TensorDict({"observation": torch.randn(2, time, OBS, generator=g),
                     "action": torch.rand(2, time, ACT, generator=g) * 2 - 1,
                     "next": {"observation": torch.randn(2, time, OBS, generator=g),
                              "reward": torch.zeros(2, time, 1), "cost": torch.ones(2, time, 1),
                              "done": torch.zeros(2, time, 1, dtype=torch.bool),
                              "terminated": torch.zeros(2, time, 1, dtype=torch.bool)}}, [2, time])
    td["next", "terminated"][:, -1] = True
    td["next", "done"][:, -1] = True
    for p in loss.cost_critic_network_params.values(True, True):
        p.data.zero_()
    with_advantages = loss.compute_advantages(td)
    expected = torch.tensor([1.875, 1.75, 1.5, 1.0]).view(1, time, 1).expand(2, time, 1)
    torch.testing.assert_close(with_advantages["cost_value_target"], expected)  # sum of 0.5^k over the rest
    assert td.get("advantage", None) is None  # the input is not written
    out = loss(td)
    assert set(out.keys()) == {"loss_critic", "loss_cost_critic"}
    assert out["loss_cost_critic"].item() == pytest.approx((expected ** 2).mean().item(), rel=1e-5)  # V_c = 0
    (out["loss_critic"] + out["loss_cost_critic"]).backward()
    assert all(p.grad is None for p in loss._actor_params())
    assert all(p.grad is not None for p in loss.critic_network_params.values(True, True))
    assert {"cost_limit"} <= set(loss.state_dict().keys())
