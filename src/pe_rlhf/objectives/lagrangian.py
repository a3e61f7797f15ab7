"""Lagrangian safe-RL losses: ``LagrangeMultiplier``, ``SACLagLoss`` (SAC-Lag) and ``PPOLagLoss`` (PPO-Lag).

Both losses solve ``max_pi J_r(pi)  s.t.  J_c(pi) <= cost_limit`` (``J_c``: mean cost per episode; the
paper's limit is 1) through the Lagrangian ``J_r - lambda * (J_c - cost_limit)``: the policy is trained on
the reward objective penalised by ``lambda`` times a cost estimate, and ``lambda >= 0`` rises while the
measured episode cost exceeds the limit. They extend TorchRL's ``SACLoss`` / ``ClipPPOLoss`` (subclasses:
the reward critics, targets, value estimators, ``set_keys`` and ``SoftUpdate`` are TorchRL's own) with a
cost critic and the penalty. ``lambda`` is updated outside the gradient step, once per collection, from
the mean episode cost: ``loss.lagrange_multiplier.update(mean_episode_cost)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, dispatch
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import ClipPPOLoss, SACLoss
from torchrl.objectives.sac import compute_rsample_log_prob
from torchrl.objectives.utils import _vmap_func, distance_loss
from torchrl.objectives.value import GAE, ValueEstimatorBase
from torchrl.objectives.value.functional import td0_return_estimate

PARAMETRIZATIONS = ("projected", "softplus", "log")


class LagrangeMultiplier(nn.Module):
    """A multiplier ``lambda >= 0`` for the constraint ``J_c <= cost_limit`` (``J_c``: mean episode cost).

    ``parametrization``: ``"projected"`` (default) keeps ``lambda`` itself as the parameter, clipped to
    ``[0, max_value]``: :meth:`update` is then the projected dual ascent
    ``lambda <- clip(lambda + lr * (J_c - cost_limit), 0, max_value)``, which reaches exactly 0 once the
    constraint holds. ``"softplus"`` / ``"log"``: ``lambda = softplus(raw)`` / ``exp(raw)``, positive by
    construction (never exactly 0); :meth:`update` is one gradient-ascent step of ``lr`` on ``raw``, for
    ``"log"`` on ``raw * (J_c - cost_limit)`` as SAC's temperature (multiplicative: ``exp(lr * violation)``).
    Gradient form: minimise :meth:`loss` with any optimizer, then call :meth:`project_`.
    ``raw`` and ``cost_limit`` are in ``state_dict``.
    """

    def __init__(self, cost_limit: float = 1.0, *, init: float = 0.0, lr: float = 0.05,
                 parametrization: str = "projected", max_value: float | None = None) -> None:
        super().__init__()
        if parametrization not in PARAMETRIZATIONS:
            raise ValueError(f"parametrization={parametrization!r}; allowed: {list(PARAMETRIZATIONS)}")
        if not (math.isfinite(init) and init >= 0 and (init > 0 or parametrization == "projected")):
            raise ValueError(f"init={init} is invalid: finite, >= 0 (> 0 for {parametrization!r})")
        if not (math.isfinite(lr) and lr > 0) or (max_value is not None and not max_value > 0):
            raise ValueError(f"lr={lr} and max_value={max_value} must be > 0")
        self.parametrization, self.lr, self.max_value = parametrization, float(lr), max_value
        raw = {"projected": init, "softplus": math.log(math.expm1(init)) if init else 0.0,
               "log": math.log(init) if init else 0.0}[parametrization]
        self.raw = nn.Parameter(torch.tensor(float(raw)))
        self.register_buffer("cost_limit", torch.tensor(float(cost_limit)))

    @property
    def value(self) -> torch.Tensor:
        """``lambda``, a scalar tensor differentiable with respect to ``raw``."""
        if self.parametrization == "projected":
            return self.raw.clamp(0.0, self.max_value)
        value = nn.functional.softplus(self.raw) if self.parametrization == "softplus" else self.raw.exp()
        return value if self.max_value is None else value.clamp(max=self.max_value)

    def loss(self, mean_episode_cost: float | torch.Tensor) -> torch.Tensor:
        """``-lambda * (J_c - cost_limit)``: descending it raises ``lambda`` while the constraint is violated."""
        violation = torch.as_tensor(mean_episode_cost, dtype=self.raw.dtype, device=self.raw.device).detach()
        multiplier = self.raw if self.parametrization == "log" else self.value  # log: d/d raw is the violation
        return -multiplier * (violation - self.cost_limit)

    def update(self, mean_episode_cost: float | torch.Tensor) -> torch.Tensor:
        """One step of size ``lr`` on :meth:`loss`, then :meth:`project_`; returns the new ``lambda``."""
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(self.loss(mean_episode_cost), self.raw)
        with torch.no_grad():
            self.raw.sub_(self.lr * grad)
        self.project_()
        return self.value.detach()

    @torch.no_grad()
    def project_(self) -> None:
        """Clip ``raw`` to the feasible set (``[0, max_value]`` for the projected form)."""
        if self.parametrization == "projected":
            self.raw.clamp_(0.0, self.max_value)


def make_cost_gae(reward_estimator: ValueEstimatorBase, cost_value_network: TensorDictModule, *,
                  cost: NestedKey, cost_value: NestedKey, cost_advantage: NestedKey,
                  cost_value_target: NestedKey, done: NestedKey, terminated: NestedKey) -> GAE:
    """A TorchRL ``GAE`` on ``("next", cost)`` with the reward estimator's ``gamma`` (and ``lmbda``, else 0.95).

    Reads ``("next", cost)``, ``("next", done)``, ``("next", terminated)`` ``(*B, T, 1)``; writes
    ``cost_value`` (root and ``next``), ``cost_advantage`` and ``cost_value_target`` ``(*B, T, 1)``.
    """
    lmbda = getattr(reward_estimator, "lmbda", 0.95)
    estimator = GAE(gamma=float(reward_estimator.gamma), lmbda=float(lmbda), value_network=cost_value_network)
    estimator.set_keys(reward=cost, value=cost_value, advantage=cost_advantage, value_target=cost_value_target,
                       done=done, terminated=terminated)
    return estimator


class SACLagLoss(SACLoss):
    """SAC-Lag: TorchRL's ``SACLoss`` plus a twin cost critic and a ``lambda``-weighted cost penalty.

    - ``loss_qvalue``, ``loss_alpha``, ``alpha``, ``entropy``: as ``SACLoss``.
    - ``loss_cost_qvalue``: twin cost critics ``Q_c`` (own target nets, no entropy term),
      ``y_c = c + gamma * (1 - terminated) * agg_k Q_c'_k(s', a')``, ``a' ~ pi(s')``; ``agg`` is
      ``cost_aggregate`` (``"max"``: pessimistic about cost, mirroring the reward's min); ``gamma`` is the
      SAC value estimator's.
    - ``loss_actor``: ``(alpha * log pi(a|s) - min_k Q_k(s, a) + lambda * agg_k Q_c_k(s, a)) / (1 + lambda)``
      on one reparametrised ``a ~ pi(s)``; the ``1 + lambda`` division (``normalize_actor_loss``, on by
      default, as OmniSafe) keeps the actor's step size bounded as ``lambda`` grows. ``lambda = 0`` gives
      ``SACLoss``'s actor loss exactly.
    - ``lagrange_multiplier`` (detached) and ``cost_qvalue`` (mean ``Q_c`` at the policy's action).

    Args:
        actor_network, qvalue_network: as ``SACLoss``.
        cost_qvalue_network: a ``TensorDictModule`` reading ``observation`` and ``action``, writing
            ``state_action_cost_value`` (default key: ``"state_action_value"``, so ``make_qvalue`` serves).
    Keyword Args:
        lagrange_multiplier: a :class:`LagrangeMultiplier` (default: ``cost_limit=1``, ``lambda = 0``).
        num_cost_qvalue_nets (2), cost_aggregate (``"max"``/``"mean"``/``"min"``), normalize_actor_loss;
            the rest goes to ``SACLoss`` (``gamma`` through ``make_value_estimator``).

    Keys (``set_keys``): ``observation`` ``(*B, O)`` (the networks' in_keys), ``action`` ``(*B, A)``,
    ``("next", "reward")``, ``("next", "cost")`` float ``(*B, 1)``, ``("next", "done")``,
    ``("next", "terminated")`` bool ``(*B, 1)``, ``("next", "observation")``.
    """

    @dataclass
    class _AcceptedKeys(SACLoss._AcceptedKeys):
        cost: NestedKey = "cost"
        state_action_cost_value: NestedKey = "state_action_value"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    cost_qvalue_network: TensorDictModule
    cost_qvalue_network_params: TensorDictParams
    target_cost_qvalue_network_params: TensorDictParams

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, qvalue_network: TensorDictModule,
                 cost_qvalue_network: TensorDictModule, *, lagrange_multiplier: LagrangeMultiplier | None = None,
                 num_cost_qvalue_nets: int = 2, cost_aggregate: str = "max", normalize_actor_loss: bool = True,
                 **sac_kwargs) -> None:
        if cost_aggregate not in ("max", "mean", "min"):
            raise ValueError(f"cost_aggregate={cost_aggregate!r}; allowed: 'max', 'mean', 'min'")
        super().__init__(actor_network, qvalue_network, **sac_kwargs)
        self.convert_to_functional(cost_qvalue_network, "cost_qvalue_network", num_cost_qvalue_nets,
                                   create_target_params=True)
        self.lagrange_multiplier = lagrange_multiplier if lagrange_multiplier is not None else LagrangeMultiplier()
        self.cost_aggregate, self.normalize_actor_loss = cost_aggregate, normalize_actor_loss
        self._make_vmap()
        self._in_keys = None

    def _make_vmap(self) -> None:
        super()._make_vmap()
        if "cost_qvalue_network" in self.__dict__:
            self._vmap_cost_qnetworkN0 = _vmap_func(self.cost_qvalue_network, (None, 0),
                                                    randomness=self.vmap_randomness, pseudo_vmap=self.deactivate_vmap)

    def _set_in_keys(self) -> None:
        super()._set_in_keys()
        if "cost_qvalue_network" in self.__dict__:
            extra = [unravel_key(("next", self.tensor_keys.cost)), *self.cost_qvalue_network.in_keys]
            self._in_keys = list({*self._in_keys, *extra})

    @property
    def out_keys(self) -> list[str]:
        if self._out_keys is None:
            self._out_keys = [*SACLoss.out_keys.fget(self), "loss_cost_qvalue", "lagrange_multiplier", "cost_qvalue"]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values) -> None:
        self._out_keys = values

    def _cost_q(self, params, tensordict: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
        """``agg_k Q_c_k(s, action)`` ``(*B)`` under ``params`` (the input is not written)."""
        td = tensordict.select(*self.cost_qvalue_network.in_keys, strict=False)
        td.set(self.tensor_keys.action, action)
        values = self._vmap_cost_qnetworkN0(td, params).get(self.tensor_keys.state_action_cost_value).squeeze(-1)
        return {"max": torch.amax, "min": torch.amin, "mean": torch.mean}[self.cost_aggregate](values, dim=0)

    def _sample(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        with set_exploration_type(ExplorationType.RANDOM), self.actor_network_params.to_module(
                self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(tensordict.select(*self.actor_network.in_keys, strict=False))
            return compute_rsample_log_prob(dist)

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        weights = self._maybe_get_priority_weight(tensordict)
        action, log_prob = self._sample(tensordict)
        td_q = tensordict.select(*self.qvalue_network.in_keys, strict=False)
        td_q.set(self.tensor_keys.action, action)
        min_q = self._vmap_qnetworkN0(td_q, self._cached_detached_qvalue_params).get(
            self.tensor_keys.state_action_value).min(0)[0].squeeze(-1)
        cost_q = self._cost_q(self.cost_qvalue_network_params.detach(), tensordict, action)
        lam = self.lagrange_multiplier.value.detach()
        loss = self._alpha * log_prob - min_q + lam * cost_q
        if self.normalize_actor_loss:
            loss = loss / (1 + lam)
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=weights)
        self._cost_qvalue_diagnostic = cost_q.detach().mean()
        return loss, {"log_prob": log_prob.detach(), "cost_qvalue": cost_q.detach()}

    def cost_qvalue_loss(self, tensordict: TensorDictBase) -> torch.Tensor:
        """TD loss of the cost critics (``distance_loss`` = SAC's ``loss_function``), summed over critics."""
        keys = self.tensor_keys
        next_td = tensordict.get("next")
        with torch.no_grad():
            next_action, _ = self._sample(next_td)
            next_cost_q = self._cost_q(self.target_cost_qvalue_network_params, next_td, next_action)
            target = td0_return_estimate(self.value_estimator.gamma, next_cost_q.unsqueeze(-1),
                                         next_td.get(keys.cost).float(),
                                         terminated=next_td.get(keys.terminated),
                                         done=next_td.get(keys.done)).squeeze(-1)
        td = tensordict.select(*self.cost_qvalue_network.in_keys, strict=False)
        pred = self._vmap_cost_qnetworkN0(td, self.cost_qvalue_network_params).get(
            keys.state_action_cost_value).squeeze(-1)
        loss = distance_loss(pred, target.expand_as(pred), loss_function=self.loss_function).sum(0)
        return self._reduce_loss(loss, tensordict=tensordict, weights=self._maybe_get_priority_weight(tensordict))

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``SACLoss``'s outputs (with the penalised actor) plus ``loss_cost_qvalue`` and diagnostics."""
        out = super().forward(tensordict)
        out.set("loss_cost_qvalue", self.cost_qvalue_loss(tensordict))
        if self.reduction != "none":
            out.set("lagrange_multiplier", self.lagrange_multiplier.value.detach())
            out.set("cost_qvalue", self._cost_qvalue_diagnostic)  # set by actor_loss in this call
        return out


class PPOLagLoss(ClipPPOLoss):
    """PPO-Lag: TorchRL's ``ClipPPOLoss`` on the penalised advantage, plus a cost value head.

    - ``loss_objective``, ``loss_entropy``, ``loss_critic`` and ``ClipPPOLoss``'s diagnostics, with the
      advantage replaced by ``(A - lambda * A_c) / (1 + lambda)`` (the division: ``normalize_penalty``, on by
      default; ``ClipPPOLoss``'s own ``normalize_advantage`` standardises the result afterwards).
    - ``loss_cost_critic``: ``cost_critic_coeff * distance(V_c(s), cost_value_target)``
      (``loss_critic_type`` as the reward critic's).
    - ``lagrange_multiplier`` (detached).

    Advantages missing from the input are computed here, with the networks' current (detached) weights:
    the reward one by ``ClipPPOLoss``'s value estimator (GAE by default), the cost one by
    :func:`make_cost_gae` (same ``gamma`` and ``lmbda``; :meth:`make_value_estimator` sets both).

    Args:
        actor_network, critic_network: as ``ClipPPOLoss``.
        cost_critic_network: a ``TensorDictModule`` reading ``observation``, writing ``cost_value``
            (default ``"state_cost_value"``) ``(*B, T, 1)``.
    Keyword Args:
        lagrange_multiplier: a :class:`LagrangeMultiplier` (default: ``cost_limit=1``, ``lambda = 0``).
        normalize_penalty, cost_critic_coeff (1.0); the rest goes to ``ClipPPOLoss``.

    Keys (``set_keys``): ``ClipPPOLoss``'s (``observation``, ``action``, ``sample_log_prob``/``action_log_prob``,
    ``advantage``, ``value_target``, ``("next", "reward" | "done" | "terminated")``) plus ``("next", "cost")``
    float ``(*B, T, 1)``, ``cost_advantage`` and ``cost_value_target`` ``(*B, T, 1)`` (computed if absent).
    The input is not written.
    """

    @dataclass
    class _AcceptedKeys(ClipPPOLoss._AcceptedKeys):
        cost: NestedKey = "cost"
        cost_value: NestedKey = "state_cost_value"
        cost_advantage: NestedKey = "cost_advantage"
        cost_value_target: NestedKey = "cost_value_target"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    cost_critic_network: TensorDictModule
    cost_critic_network_params: TensorDictParams
    target_cost_critic_network_params: TensorDictParams  # never created; declared so torchrl does not warn

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, critic_network: TensorDictModule,
                 cost_critic_network: TensorDictModule, *, lagrange_multiplier: LagrangeMultiplier | None = None,
                 normalize_penalty: bool = True, cost_critic_coeff: float = 1.0, **ppo_kwargs) -> None:
        super().__init__(actor_network, critic_network, **ppo_kwargs)
        self.convert_to_functional(cost_critic_network, "cost_critic_network")
        self.lagrange_multiplier = lagrange_multiplier if lagrange_multiplier is not None else LagrangeMultiplier()
        self.normalize_penalty, self.cost_critic_coeff = normalize_penalty, float(cost_critic_coeff)
        self.__dict__["_cost_value_estimator"] = None  # not a submodule: built lazily, kept out of state_dict
        self._in_keys = None

    @property
    def cost_value_estimator(self) -> GAE:
        if self.__dict__["_cost_value_estimator"] is None:
            keys = self.tensor_keys
            self.__dict__["_cost_value_estimator"] = make_cost_gae(
                self.value_estimator, self.cost_critic_network, cost=keys.cost, cost_value=keys.cost_value,
                cost_advantage=keys.cost_advantage, cost_value_target=keys.cost_value_target, done=keys.done,
                terminated=keys.terminated)
        return self.__dict__["_cost_value_estimator"]

    def make_value_estimator(self, value_type=None, **hyperparams):
        out = super().make_value_estimator(value_type, **hyperparams)
        self.__dict__["_cost_value_estimator"] = None  # rebuilt with the new gamma / lmbda
        return out

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        super()._forward_value_estimator_keys(**kwargs)
        self.__dict__["_cost_value_estimator"] = None  # rebuilt with the new keys

    def _set_in_keys(self) -> None:
        super()._set_in_keys()
        if "cost_critic_network" in self.__dict__:
            extra = [unravel_key(("next", self.tensor_keys.cost)), *self.cost_critic_network.in_keys]
            self._in_keys = list({*self._in_keys, *extra})

    @property
    def out_keys(self) -> list[str]:
        if self._out_keys is None:
            # ClipPPOLoss returns explained_variance without listing it (torchrl 0.14): listed here, or
            # select_out_keys and keyword calls would not know it
            variance = ["explained_variance"] if self._has_critic and self.log_explained_variance else []
            self._out_keys = [*ClipPPOLoss.out_keys.fget(self), *variance, "loss_cost_critic", "lagrange_multiplier"]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values) -> None:
        self._out_keys = values

    def loss_cost_critic(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``cost_critic_coeff * distance(V_c(s), cost_value_target)``, reduced."""
        keys = self.tensor_keys
        td = tensordict.select(*self.cost_critic_network.in_keys, strict=False)
        with self.cost_critic_network_params.to_module(self.cost_critic_network, preserve_module_state=False):
            value = self.cost_critic_network(td).get(keys.cost_value)
        loss = distance_loss(value, tensordict.get(keys.cost_value_target), loss_function=self.loss_critic_type)
        return self.cost_critic_coeff * self._reduce_loss(loss, tensordict).squeeze(-1)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        td = tensordict.clone(False)
        if td.get(keys.advantage, None) is None:
            self.value_estimator(td, params=self._cached_critic_network_params_detached,
                                 target_params=self.target_critic_network_params)
        if td.get(keys.cost_advantage, None) is None:
            self.cost_value_estimator(td, params=self.cost_critic_network_params.detach())
        lam = self.lagrange_multiplier.value.detach()
        advantage = td.get(keys.advantage) - lam * td.get(keys.cost_advantage)
        td.set(keys.advantage, advantage / (1 + lam) if self.normalize_penalty else advantage)
        out = super().forward(td)
        out.set("loss_cost_critic", self.loss_cost_critic(td))
        if self.reduction != "none":
            out.set("lagrange_multiplier", lam)
        return out
