"""``ProxyValueLoss``: reward-free learning from takeovers with bounded proxy values (PVP), a TorchRL ``LossModule``.

Proxy Value Propagation (Peng et al., NeurIPS 2023) replaces HACO's unbounded gap with two fixed labels and lets
plain TD learning carry them to the states the mentor never touched. One update reads a batch of transitions
``(s, a_AV, a_exec, I, I_start, s')`` (the keys :class:`~pe_rlhf.transforms.InterventionTransform` writes) and
returns:

- ``loss_proxy``: on takeover rows only (``I = 1``), the executed action is labelled ``+B`` and the agent's
  proposal ``-B``, ``B = q_value_bound``:
  ``sum_k mean_{I=1} [(Q_k(s, a_exec) - B)^2 + (Q_k(s, a_AV) - (-B))^2]``; 0 on a batch without a takeover.
  During a PE-RLHF takeover the executed action is the hybrid's (mentor or physics): the loss need not know which
  (leaving physics' executed actions unlabelled was measured twice and lost: docs/experiments/learner.md).
  ``proxy_reduction="batch"`` is PVP's released code instead (``pvp_td3.py``): both squared errors averaged over the
  *whole* batch and scaled by its share of takeover rows, so a row without a takeover, where ``a_AV = a_exec``, is
  pulled to ``+B`` and ``-B`` at once, i.e. towards 0; and ``loss_td`` weighted 0.5:
  ``mean(I) * sum_k [mean (Q_k(s, a_exec) - B)^2 + mean (Q_k(s, a_AV) + B)^2]``.
- ``loss_td``: zero-reward TD on every row at the executed action, twin critics, TD3's target
  ``y = gamma * (1 - terminated) * min_k Q'_k(s', clip(pi'(s') + clip(N(0, sigma), -c, c), -1, 1))``,
  ``sum_k mean (Q_k(s, a_exec) - y)^2``. With ``mask_td_at_takeover_start`` the rows where a takeover starts
  are left out of it (PVP's mask: that step's value is the proxy label alone). TD carries a takeover's ``-B`` back
  along the agent's steps that led to it (``-gamma^k B``); leaving the step before a takeover out of TD was measured
  and lost (docs/experiments/learner.md).
- ``loss_actor``: a deterministic actor that maximises the first critic, ``-mean Q_1(s, pi(s))`` (critic
  parameters detached), plus ``bc_weight * mean_{I=1} ||pi(s) - a_exec||^2`` (PVP4Real's behaviour cloning on
  takeover rows). The actor's term is computed on every ``policy_delay``-th call (TD3's delay: calls
  ``policy_delay``, ``2 * policy_delay``, ...); on the calls in between ``loss_actor`` is a constant 0 and the
  actor is not evaluated. The call count is a buffer, saved with the module's state. (Inverted gradients in place
  of the tanh's derivative were measured and lost: docs/experiments/learner.md.)
- diagnostics (detached): ``td_loss``, ``proxy_loss``, ``bc_loss``, ``q_behavior`` (mean ``Q`` at the executed
  action on takeover rows), ``q_agent`` (at the agent's proposal on takeover rows), ``q_free`` (at the executed
  action on rows without a takeover), ``td_error`` (mean absolute), ``intervention_rate``, ``actor_saturation``
  (the share of the actor's action entries beyond 0.99 in magnitude, on the calls that evaluate the actor); each
  is 0 where its rows are missing from the batch.

Default keys (``set_keys`` renames): root ``observation`` (through the networks' in_keys) and ``action`` = the
agent's proposal ``a_AV`` float ``(..., A)``; under ``next``: ``behavior_action`` ``(..., A)``, ``intervention`` and
``intervention_start`` bool ``(..., 1)``, ``terminated`` bool ``(..., 1)`` and ``observation``. The reward is never
read. Any batch shape (flattened to one dim); the input tensordict is read, never written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import _vmap_func

from pe_rlhf.objectives.contract import KeyedLoss, TakeoverKeys, next_keys


PROXY_REDUCTIONS = ("takeover_rows", "batch")  # ProxyValueLoss.proxy_reduction


class ProxyValueLoss(KeyedLoss, LossModule):
    """PVP's bounded proxy values on takeover rows, zero-reward TD3 on every row, a deterministic actor.

    Args:
        actor_network: a deterministic actor reading ``observation`` and writing ``action`` in [-1, 1]
            (:func:`pe_rlhf.modules.make_deterministic_actor`); a target copy is kept.
        qvalue_network: a ``TensorDictModule`` reading ``observation`` and ``action``, writing
            ``state_action_value``; copied into ``num_qvalue_nets`` critics with target copies.

    Keyword Args:
        q_value_bound: ``B``, the label of the executed action (``+B``) and of the agent's proposal (``-B``).
        gamma: the discount of the zero-reward TD term.
        num_qvalue_nets: critics (TD3's twin: 2); the TD target takes their minimum.
        target_noise, target_noise_clip: TD3's target smoothing (sigma 0.2 clipped at 0.5).
        policy_delay: the actor is updated every ``policy_delay``-th call (TD3: 2).
        bc_weight: weight of behaviour cloning toward the executed action on takeover rows (0: off).
        mask_td_at_takeover_start: leave takeover-start rows out of the TD term (PVP's mask).
        proxy_reduction: ``"takeover_rows"`` (the proxy labels on takeover rows only) or ``"batch"`` (PVP's released
            code: over the whole batch, scaled by the takeover share, and TD weighted 0.5; module docstring).
    """

    @dataclass
    class _AcceptedKeys(TakeoverKeys):
        """Keys the loss reads; ``set_keys(action=..., behavior_action=...)`` renames them."""

        state_action_value: NestedKey = "state_action_value"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    OUTPUTS = ("loss_qvalue", "loss_actor", "td_loss", "proxy_loss", "bc_loss", "q_behavior", "q_agent", "q_free",
               "td_error", "intervention_rate", "actor_saturation")
    actor_network: TensorDictModule
    qvalue_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(self, actor_network: TensorDictModule, qvalue_network: TensorDictModule, *,
                 q_value_bound: float = 1.0, gamma: float = 0.99, num_qvalue_nets: int = 2,
                 target_noise: float = 0.2, target_noise_clip: float = 0.5, policy_delay: int = 2,
                 bc_weight: float = 0.0, mask_td_at_takeover_start: bool = False,
                 proxy_reduction: str = "takeover_rows") -> None:
        super().__init__()
        if proxy_reduction not in PROXY_REDUCTIONS:
            raise ValueError(f"ProxyValueLoss proxy_reduction={proxy_reduction!r} is invalid: allowed "
                             f"{list(PROXY_REDUCTIONS)}")
        self.proxy_reduction = proxy_reduction
        for name, value, low in (("q_value_bound", q_value_bound, 0.0), ("target_noise", target_noise, 0.0),
                                 ("target_noise_clip", target_noise_clip, 0.0), ("bc_weight", bc_weight, 0.0)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < low or (name == "q_value_bound" and value == 0):
                raise ValueError(f"ProxyValueLoss {name}={value!r} is invalid: a finite number "
                                 f"{'> 0' if name == 'q_value_bound' else '>= 0'}")
        if not (isinstance(gamma, (int, float)) and 0.0 <= gamma <= 1.0):
            raise ValueError(f"ProxyValueLoss gamma={gamma!r} is invalid: a number in [0, 1]")
        for name, value in (("num_qvalue_nets", num_qvalue_nets), ("policy_delay", policy_delay)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ProxyValueLoss {name}={value!r} is invalid: an int >= 1")
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        self.convert_to_functional(qvalue_network, "qvalue_network", num_qvalue_nets, create_target_params=True)
        self.q_value_bound, self.gamma, self.num_qvalue_nets = float(q_value_bound), float(gamma), num_qvalue_nets
        self.target_noise, self.target_noise_clip = float(target_noise), float(target_noise_clip)
        self.policy_delay, self.bc_weight = policy_delay, float(bc_weight)
        self.mask_td_at_takeover_start = bool(mask_td_at_takeover_start)
        self.register_buffer("calls", torch.zeros((), dtype=torch.long))
        self._vmap_q = _vmap_func(self.qvalue_network, (None, 0))

    # -- the TorchRL contract (pe_rlhf.objectives.contract: in_keys, out_keys, make_value_estimator TD0 only) ----
    def _loss_in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        states = self.state_keys
        flags = [keys.intervention, keys.intervention_start]
        return [keys.action, keys.behavior_action, *flags, *next_keys([keys.terminated]), *self.actor_network.in_keys,
                *states, *next_keys(self.actor_network.in_keys), *next_keys(states)]

    def _loss_out_keys(self) -> list[str]:
        return list(self.OUTPUTS)

    # -- values --------------------------------------------------------------------------------
    @property
    def policy_action_key(self) -> NestedKey:
        """The key the actor writes and the critics read their action from (the networks' own, ``action``); the
        stored proposal may live under another name (``tensor_keys.action``)."""
        out = self.actor_network.out_keys
        return "action" if "action" in out else out[0]

    @property
    def state_keys(self) -> list[NestedKey]:
        """The critics' inputs other than the action (the loss sets the action it values)."""
        return [k for k in self.qvalue_network.in_keys if k != self.policy_action_key]

    def _q(self, params, tensordict: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
        """``(copies, rows)`` values of the critics under ``params`` at ``action``."""
        td = tensordict.select(*self.state_keys, strict=False)
        td.set(self.policy_action_key, action)
        return self._vmap_q(td, params).get(self.tensor_keys.state_action_value).squeeze(-1)

    def _act(self, params, tensordict: TensorDictBase) -> torch.Tensor:
        """The deterministic actor's action under ``params`` (the input is not written)."""
        td = tensordict.select(*self.actor_network.in_keys, strict=False)
        with params.to_module(self.actor_network):
            out = self.actor_network(td)
        return out.get(self.policy_action_key)

    def td_target(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``(rows,)``: ``gamma * (1 - terminated) * min_k Q'_k(s', smoothed pi'(s'))``, zero reward, no grad."""
        next_td = tensordict.get("next")
        with torch.no_grad():
            next_action = self._act(self.target_actor_network_params, next_td)
            noise = (torch.randn_like(next_action) * self.target_noise).clamp(-self.target_noise_clip,
                                                                              self.target_noise_clip)
            next_action = (next_action + noise).clamp(-1.0, 1.0)
            next_q = self._q(self.target_qvalue_network_params, next_td, next_action).min(0)[0]
            not_terminal = 1.0 - next_td.get(self.tensor_keys.terminated).reshape(-1).float()
            return self.gamma * not_terminal * next_q

    # -- the loss ------------------------------------------------------------------------------
    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys = self.tensor_keys
        if tensordict.batch_dims != 1:  # takeover rows are indexed along one batch dim
            tensordict = tensordict.reshape(-1)
        takeover = tensordict.get(keys.intervention).reshape(-1).bool()
        behavior, agent = tensordict.get(keys.behavior_action), tensordict.get(keys.action)
        rows = tensordict.shape[0]
        # one critic pass: the executed action on every row, then the agent's proposal on the takeover rows (on
        # every row where the proxy term reads the whole batch)
        state = tensordict.select(*self.state_keys, strict=False)
        labelled = takeover if self.proxy_reduction == "takeover_rows" else torch.ones_like(takeover)
        both = torch.cat([state, state[labelled]], 0)
        q_all = self._q(self.qvalue_network_params, both, torch.cat([behavior, agent[labelled]], 0))
        q_exec, q_agent = q_all[:, :rows], q_all[:, rows:]

        target = self.td_target(tensordict)
        td_rows = torch.ones_like(takeover)
        if self.mask_td_at_takeover_start:
            td_rows = ~tensordict.get(keys.intervention_start).reshape(-1).bool()
        td_error = (q_exec - target)[:, td_rows]
        loss_td = td_error.pow(2).mean(-1).sum(0) if td_rows.any() else q_all.new_zeros(())
        zero = q_all.new_zeros(())
        bound = self.q_value_bound
        if self.proxy_reduction == "batch":  # PVP's released code: q_agent holds every row
            loss_td = 0.5 * loss_td
            loss_proxy = takeover.float().mean() * ((q_exec - bound).pow(2).mean(-1)
                                                    + (q_agent + bound).pow(2).mean(-1)).sum(0)
            q_agent = q_agent[:, takeover]
        elif takeover.any():  # q_agent holds the takeover rows only
            loss_proxy = ((q_exec[:, takeover] - bound).pow(2).mean(-1) + (q_agent + bound).pow(2).mean(-1)).sum(0)
        else:
            loss_proxy = zero

        loss_actor, loss_bc, saturation = zero, zero, zero
        if (int(self.calls) + 1) % self.policy_delay == 0:  # after every policy_delay-th critic step
            action = self._act(self.actor_network_params, tensordict)
            q_first = self._q(self.qvalue_network_params.detach()[:1], tensordict, action)[0]
            loss_actor = -q_first.mean()
            saturation = (action.detach().abs() > 0.99).float().mean()
            if self.bc_weight > 0 and takeover.any():
                loss_bc = (action[takeover] - behavior[takeover]).pow(2).sum(-1).mean()
                loss_actor = loss_actor + self.bc_weight * loss_bc
        self.calls += 1

        detached = q_exec.detach().mean(0)
        return TensorDict({
            "loss_qvalue": loss_td + loss_proxy,
            "loss_actor": loss_actor,
            "td_loss": loss_td.detach(),
            "proxy_loss": loss_proxy.detach(),
            "bc_loss": loss_bc.detach(),
            "q_behavior": detached[takeover].mean() if takeover.any() else zero,
            "q_agent": q_agent.detach().mean() if takeover.any() else zero,
            "q_free": detached[~takeover].mean() if (~takeover).any() else zero,
            "td_error": td_error.detach().abs().mean() if td_error.numel() else zero,
            "intervention_rate": takeover.float().mean(),
            "actor_saturation": saturation,
        }, batch_size=[])
