"""``CPOLoss``: Constrained Policy Optimization (Achiam et al., 2017) for a Gaussian TorchRL actor.

One policy update, :meth:`CPOLoss.policy_step`, on an on-policy batch:

1. surrogates ``L_r = mean(ratio * A)``, ``L_c = mean(ratio * A_c)``, ``ratio = pi_theta(a|s) / pi_old(a|s)``;
   ``g = grad L_r``, ``b = grad L_c`` at ``theta_old``;
2. ``H``: the Hessian of the mean ``KL(pi_old || pi_theta)`` (the Fisher matrix), used only through products
   ``H v`` (double backprop, plus ``cg_damping * v``); ``H^-1 g`` and ``H^-1 b`` by :func:`conjugate_gradient`;
3. the step ``x`` solves ``max g^T x  s.t.  c + b^T x <= 0,  x^T H x / 2 <= target_kl`` with
   ``c = J_c - cost_limit`` (``J_c``: mean episode cost), through the dual (:func:`cpo_direction`); when no
   ``x`` satisfies both (``c > 0`` and ``c^2 / s > 2 target_kl``) the recovery step
   ``x = -sqrt(2 target_kl / s) H^-1 b`` purely decreases the cost;
4. backtracking line search on ``theta_old + backtrack_ratio^j x``: the first step with ``KL <= target_kl``,
   a surrogate cost change ``<= max(-c, 0)`` (stay feasible, or decrease the cost when infeasible) and, when
   ``c < 0``, a positive surrogate reward gain is kept; none: the policy is left unchanged.

Signs: the paper's appendix solves the minimisation form (its ``g`` is a loss gradient); here ``g`` is the
reward's ascent direction, so ``nu* = (lambda* c + r)_+ / s`` and ``x* = H^-1 (g - nu* b) / lambda*``.
Units: as OmniSafe, ``c`` is in episode-cost units and ``b^T x`` is the change of the mean cost advantage
(no ``1 / (1 - gamma)`` factor). The value nets are trained by ordinary gradient steps on :meth:`forward`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch.distributions import Normal, kl_divergence
from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import (
    ValueEstimators,
    dispatch_value_estimator,
    distance_loss,
)

from pe_rlhf.objectives.contract import KeyedLoss, next_keys
from pe_rlhf.objectives.lagrangian import make_cost_gae

CPO_CASES = ("recovery", "infeasible_start", "feasible_start", "constraint_inactive")  # c > 0 | c >= 0 | c < 0
RECOVERY, INFEASIBLE_START, FEASIBLE_START, CONSTRAINT_INACTIVE = range(len(CPO_CASES))


def conjugate_gradient(matrix_vector_product: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor,
                       iterations: int = 10, residual_tol: float = 1e-10) -> torch.Tensor:
    """Approximate ``A^-1 b`` for a symmetric positive-definite ``A`` known only through ``v -> A v``."""
    x, residual = torch.zeros_like(b), b.clone()
    direction, residual_sq = b.clone(), b @ b
    for _ in range(iterations):
        if residual_sq <= residual_tol:
            break
        a_direction = matrix_vector_product(direction)
        step = residual_sq / (direction @ a_direction)
        x += step * direction
        residual -= step * a_direction
        new_residual_sq = residual @ residual
        direction = residual + (new_residual_sq / residual_sq) * direction
        residual_sq = new_residual_sq
    return x


@dataclass
class CPODirection:
    """The full step ``x`` of one CPO update, its case (an index into ``CPO_CASES``) and dual variables."""

    step: torch.Tensor
    case: int
    lagrange_kl: float  # lambda*, the trust-region multiplier (0 for the recovery step)
    lagrange_cost: float  # nu*, the cost-constraint multiplier


def cpo_direction(g_dir: torch.Tensor, b_dir: torch.Tensor, q: float, r: float, s: float, c: float,
                  target_kl: float) -> CPODirection:
    """Solve ``max g^T x  s.t.  c + b^T x <= 0,  x^T H x / 2 <= target_kl`` from ``g_dir = H^-1 g``,
    ``b_dir = H^-1 b``, ``q = g^T H^-1 g``, ``r = b^T H^-1 g``, ``s = b^T H^-1 b``, ``c`` (module docstring)."""
    eps = 1e-8
    if s <= eps or (c < 0 and c * c / s > 2 * target_kl):  # the constraint cannot bind inside the region
        if c >= 0 and s <= eps:
            return CPODirection(torch.zeros_like(g_dir), RECOVERY, 0.0, 0.0)  # no cost gradient to follow
        step = math.sqrt(2 * target_kl / max(q, eps)) * g_dir
        return CPODirection(step, CONSTRAINT_INACTIVE, math.sqrt(q / (2 * target_kl)), 0.0)
    big_a, big_b = max(q - r * r / s, 0.0), 2 * target_kl - c * c / s
    if c > 0 and big_b < 0:  # no step satisfies the linearised constraint in the trust region: recover
        nu = math.sqrt(2 * target_kl / s)
        return CPODirection(-nu * b_dir, RECOVERY, 0.0, nu)
    # lambda > 0 splits in Lambda_a = {lambda c + r > 0} (nu > 0) and Lambda_b (nu = 0); the dual is convex
    # on each, so projecting its unconstrained minimiser onto the interval gives that interval's best.
    c = c if abs(c) > eps else eps
    edge = max(-r / c, 0.0)
    interval_a, interval_b = ((edge, math.inf), (0.0, edge)) if c > 0 else ((0.0, edge), (edge, math.inf))

    def dual_a(lam):  # the dual with nu* = (lambda c + r) / s substituted
        return big_a / (2 * lam) + lam * big_b / 2 - r * c / s

    def dual_b(lam):  # nu* = 0: the plain trust-region dual
        return q / (2 * lam) + lam * target_kl

    candidates = []
    if interval_a[1] > interval_a[0] and big_b > 0:
        lam = min(max(math.sqrt(big_a / big_b), interval_a[0]), interval_a[1])
        candidates.append((dual_a(max(lam, eps)), max(lam, eps)))
    lam = min(max(math.sqrt(q / (2 * target_kl)), interval_b[0]), interval_b[1])
    candidates.append((dual_b(max(lam, eps)), max(lam, eps)))
    lam = min(candidates)[1]  # the dual is minimised
    nu = max(lam * c + r, 0.0) / s
    return CPODirection((g_dir - nu * b_dir) / lam, FEASIBLE_START if c < 0 else INFEASIBLE_START, lam, nu)


def base_normal(dist) -> Normal:
    """The Gaussian under a (Tanh)Normal / Independent wrapper: KL is invariant under the tanh bijection."""
    while not isinstance(dist, Normal):
        dist = dist.base_dist
    return dist


def _flat(tensors) -> torch.Tensor:
    return torch.cat([t.reshape(-1) for t in tensors])


class CPOLoss(KeyedLoss, LossModule):
    """CPO's value losses (:meth:`forward`) and its constrained trust-region policy update (:meth:`policy_step`).

    Args:
        actor_network: a ``ProbabilisticActor`` with a ``Normal``/``TanhNormal``-type distribution reading
            ``observation``; its parameters are moved by :meth:`policy_step` only.
        critic_network: reads ``observation``, writes ``value`` (``"state_value"``) ``(*B, T, 1)``.
        cost_critic_network: reads ``observation``, writes ``cost_value`` (``"state_cost_value"``).
    Keyword Args:
        cost_limit (1.0, per episode), target_kl (0.01), cg_iterations (10), cg_damping (0.1),
        backtrack_ratio (0.8), max_backtracks (15), loss_critic_type (``"l2"``), reduction (``"mean"``).

    Keys (``set_keys``): ``observation``, ``action`` ``(*B, T, A)``, ``("next", "reward" | "cost")`` float and
    ``("next", "done" | "terminated")`` bool ``(*B, T, 1)``; ``advantage``, ``value_target``,
    ``cost_advantage``, ``cost_value_target`` ``(*B, T, 1)``: computed by :meth:`compute_advantages` (GAE,
    ``make_value_estimator`` sets ``gamma``/``lmbda`` for both) when absent. :meth:`forward` returns
    ``loss_critic`` and ``loss_cost_critic``; the input is not written.
    """

    @dataclass
    class _AcceptedKeys:
        action: NestedKey = "action"
        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"
        value: NestedKey = "state_value"
        cost_advantage: NestedKey = "cost_advantage"
        cost_value_target: NestedKey = "cost_value_target"
        cost_value: NestedKey = "state_cost_value"
        reward: NestedKey = "reward"
        cost: NestedKey = "cost"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE
    actor_network: ProbabilisticTensorDictSequential
    critic_network: TensorDictModule
    cost_critic_network: TensorDictModule
    actor_network_params: TensorDictParams
    critic_network_params: TensorDictParams
    cost_critic_network_params: TensorDictParams
    # never created; declared so torchrl does not warn
    target_actor_network_params: TensorDictParams
    target_critic_network_params: TensorDictParams
    target_cost_critic_network_params: TensorDictParams

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, critic_network: TensorDictModule,
                 cost_critic_network: TensorDictModule, *, cost_limit: float = 1.0, target_kl: float = 0.01,
                 cg_iterations: int = 10, cg_damping: float = 0.1, backtrack_ratio: float = 0.8,
                 max_backtracks: int = 15, loss_critic_type: str = "l2", reduction: str = "mean") -> None:
        super().__init__()
        if not (target_kl > 0 and 0 < backtrack_ratio < 1 and cg_damping >= 0):
            raise ValueError("CPOLoss needs target_kl > 0, 0 < backtrack_ratio < 1 and cg_damping >= 0")
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(critic_network, "critic_network")
        self.convert_to_functional(cost_critic_network, "cost_critic_network")
        self.register_buffer("cost_limit", torch.tensor(float(cost_limit)))
        self.target_kl, self.cg_iterations, self.cg_damping = float(target_kl), cg_iterations, cg_damping
        self.backtrack_ratio, self.max_backtracks = backtrack_ratio, max_backtracks
        self.loss_critic_type, self.reduction = loss_critic_type, reduction
        self.__dict__["_cost_value_estimator"] = None  # built lazily, kept out of state_dict

    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.GAE,)

    def _loss_out_keys(self) -> list[str]:
        return ["loss_critic", "loss_cost_critic"]

    def _loss_in_keys(self) -> list[NestedKey]:
        """What :meth:`forward` reads when the advantages are absent (GAE computes them): the critics' inputs now
        and one step later, the step's reward, cost and flags. The policy step also reads the action."""
        keys = self.tensor_keys
        states = [*self.critic_network.in_keys, *self.cost_critic_network.in_keys]
        step = [keys.reward, keys.cost, keys.done, keys.terminated]
        return [*self.actor_network.in_keys, keys.action, *states, *next_keys([*step, *states])]

    # -- advantages ----------------------------------------------------------------------------
    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        if value_type is None or isinstance(value_type, (str, ValueEstimators)):
            self.check_value_type(value_type)  # one clear line naming GAE, before TorchRL's dispatch
        value_type, hp = self._prepare_value_estimator_kwargs(value_type, **hyperparams)
        if value_type is not None:
            keys = self.tensor_keys
            dispatch_value_estimator(self, value_type, supported=(ValueEstimators.GAE,), tensor_keys={
                "advantage": keys.advantage, "value_target": keys.value_target, "value": keys.value,
                "reward": keys.reward, "done": keys.done, "terminated": keys.terminated}, **hp)
        self.__dict__["_cost_value_estimator"] = None  # rebuilt with the new gamma / lmbda
        return self

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            keys = self.tensor_keys
            self._value_estimator.set_keys(advantage=keys.advantage, value_target=keys.value_target,
                                           value=keys.value, reward=keys.reward, done=keys.done,
                                           terminated=keys.terminated)
        self.__dict__["_cost_value_estimator"] = None
        self._set_in_keys()

    @property
    def cost_value_estimator(self):
        if self.__dict__["_cost_value_estimator"] is None:
            keys = self.tensor_keys
            self.__dict__["_cost_value_estimator"] = make_cost_gae(
                self.value_estimator, self.cost_critic_network, cost=keys.cost, cost_value=keys.cost_value,
                cost_advantage=keys.cost_advantage, cost_value_target=keys.cost_value_target, done=keys.done,
                terminated=keys.terminated)
        return self.__dict__["_cost_value_estimator"]

    def compute_advantages(self, tensordict: TensorDictBase) -> TensorDictBase:
        """A shallow copy of ``tensordict`` holding the reward and cost advantages and value targets."""
        td = tensordict.clone(False)
        if td.get(self.tensor_keys.advantage, None) is None:
            self.value_estimator(td, params=self.critic_network_params.detach())
        if td.get(self.tensor_keys.cost_advantage, None) is None:
            self.cost_value_estimator(td, params=self.cost_critic_network_params.detach())
        return td

    # -- value losses ------------------------------------------------------------------------------
    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        td, keys, out = self.compute_advantages(tensordict), self.tensor_keys, {}
        for name, network, value_key, target_key in (
                ("loss_critic", "critic_network", keys.value, keys.value_target),
                ("loss_cost_critic", "cost_critic_network", keys.cost_value, keys.cost_value_target)):
            module = getattr(self, network)
            with getattr(self, network + "_params").to_module(module, preserve_module_state=False):
                value = module(td.select(*module.in_keys, strict=False)).get(value_key)
            loss = distance_loss(value, td.get(target_key), loss_function=self.loss_critic_type)
            out[name] = self._reduce_loss(loss, td).squeeze(-1)
        return TensorDict(out, batch_size=[])

    # -- the policy update -----------------------------------------------------------------------------
    def _actor_params(self) -> list[torch.Tensor]:
        return [p for p in self.actor_network_params.values(True, True) if p.requires_grad]

    def policy(self, tensordict: TensorDictBase) -> tuple[Normal, torch.Tensor]:
        """The current policy's base Gaussian at ``observation`` and its log-prob of ``action`` ``(*B, T)``."""
        action = tensordict.get(self.tensor_keys.action)
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(tensordict.select(*self.actor_network.in_keys, strict=False))
        log_prob = dist.log_prob(action)
        return base_normal(dist), log_prob.sum(-1) if log_prob.shape == action.shape else log_prob

    def _surrogates(self, td: TensorDictBase, old: tuple[Normal, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """``(L_r, L_c, mean KL(old || current))`` at the current actor parameters."""
        normal, log_prob = self.policy(td)
        ratio = (log_prob - old[1]).exp()
        reward = (ratio * td.get(self.tensor_keys.advantage).squeeze(-1)).mean()
        cost = (ratio * td.get(self.tensor_keys.cost_advantage).squeeze(-1)).mean()
        return reward, cost, kl_divergence(old[0], normal).sum(-1).mean()

    def _set_actor_params(self, params: list[torch.Tensor], flat: torch.Tensor) -> None:
        with torch.no_grad():
            offset = 0
            for p in params:
                p.copy_(flat[offset: offset + p.numel()].view_as(p))
                offset += p.numel()

    def policy_step(self, tensordict: TensorDictBase, mean_episode_cost: float | torch.Tensor) -> TensorDict:
        """One CPO update of the actor in place; returns diagnostics (scalars): ``case`` (index in
        ``CPO_CASES``), ``lagrange_kl``, ``lagrange_cost``, ``constraint_violation`` (``c``), ``step_fraction``
        (0: rejected), ``kl``, ``surrogate_reward_gain``, ``surrogate_cost_change``."""
        td = self.compute_advantages(tensordict)
        with torch.no_grad():
            old_normal, old_log_prob = self.policy(td)
        old = (Normal(old_normal.loc.detach(), old_normal.scale.detach()), old_log_prob.detach())
        params = self._actor_params()
        reward, cost, kl = self._surrogates(td, old)
        g = _flat(torch.autograd.grad(reward, params, retain_graph=True))
        b = _flat(torch.autograd.grad(cost, params, retain_graph=True))
        kl_grad = _flat(torch.autograd.grad(kl, params, create_graph=True))

        def fisher_vector_product(v: torch.Tensor) -> torch.Tensor:
            return _flat(torch.autograd.grad(kl_grad @ v, params, retain_graph=True)) + self.cg_damping * v

        g_dir = conjugate_gradient(fisher_vector_product, g, self.cg_iterations)
        b_dir = conjugate_gradient(fisher_vector_product, b, self.cg_iterations)
        c = float(mean_episode_cost) - self.cost_limit.item()
        direction = cpo_direction(g_dir, b_dir, (g @ g_dir).item(), (b @ g_dir).item(), (b @ b_dir).item(), c,
                                  self.target_kl)
        fraction, stats = self.line_search(td, old, direction.step, c)
        return TensorDict({"case": direction.case, "lagrange_kl": direction.lagrange_kl,
                           "lagrange_cost": direction.lagrange_cost, "constraint_violation": c,
                           "step_fraction": fraction, **stats}, batch_size=[])

    @torch.no_grad()
    def line_search(self, tensordict: TensorDictBase, old: tuple[Normal, torch.Tensor], step: torch.Tensor,
                    constraint_violation: float) -> tuple[float, dict[str, float]]:
        """Backtrack on ``theta_old + backtrack_ratio^j * step`` (module docstring, 4.); the actor keeps the
        first accepted point (returns its fraction) or its old parameters (returns 0). ``tensordict`` holds
        the advantages; ``old``: ``(pi_old's base Gaussian, its log-probs of the actions)``."""
        params = self._actor_params()
        theta_old = _flat(params).clone()
        reward_old, cost_old, _ = self._surrogates(tensordict, old)
        allowed_cost_change = max(-constraint_violation, 0.0)
        for j in range(self.max_backtracks):
            fraction = self.backtrack_ratio ** j
            self._set_actor_params(params, theta_old + fraction * step)
            reward, cost, kl = self._surrogates(tensordict, old)
            stats = {"kl": kl.item(), "surrogate_reward_gain": (reward - reward_old).item(),
                     "surrogate_cost_change": (cost - cost_old).item()}
            if (math.isfinite(stats["kl"]) and stats["kl"] <= self.target_kl
                    and stats["surrogate_cost_change"] <= allowed_cost_change
                    and (constraint_violation >= 0 or stats["surrogate_reward_gain"] > 0)):
                return fraction, stats
        self._set_actor_params(params, theta_old)
        return 0.0, {"kl": 0.0, "surrogate_reward_gain": 0.0, "surrogate_cost_change": 0.0}
