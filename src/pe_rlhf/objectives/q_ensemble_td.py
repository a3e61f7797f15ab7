"""``QEnsembleTDLoss``: TD regression of PE-RLHF's Q-ensemble estimator (Sec. "Ensemble of estimator Q-networks").

The paper trains K critics ``Q_k`` (same architecture, different init) on the warm-up data with the environment
reward, so ``Q`` estimates the value of the warm-up (expert / physics) policy::

    a'  = clip(a_next + N(0, target_noise), -1, 1)
    y   = r + gamma * (1 - terminated) * mean_k Q'_k(s', a')      (no gradient)
    L   = (y - mean_k Q_k(s, a))^2                 regression="mean"   (the paper's)
    L   = mean_k (y - Q_k(s, a))^2                 regression="member" (keeps members diverse)

``a_next`` is the warm-up policy's action at ``s'``, read from the data (``pe_rlhf.modules.add_next_actions``
builds it from recorded trajectories); ``Q'`` is a target copy of the ensemble, moved towards it by TorchRL's
``SoftUpdate`` (``Q' <- (1 - tau) Q' + tau Q``). :func:`pe_rlhf.objectives.fit_q_ensemble` is the loop that
samples minibatches and steps an optimiser and the updater on this loss.

``regression="mean"`` is the paper's form: only the members' *mean* is regressed to ``y``. Every member
receives the same residual, so nothing pulls a single member towards ``y``: the members are not individually
Q estimates, and their disagreement is an artefact of init and of that shared gradient (it typically *grows*
during the fit) rather than a measure of what the data leaves unknown. ``regression="member"`` regresses each
member to ``y`` (mean over members of the squared errors): every member is a Q estimate, they agree where the
data pins them down and stay diverse where it does not (the usual ensemble / REDQ recipe), so the spread is
usable by ``HybridActionSelector(variance_threshold=...)``. The means learned by both are comparably good.
Measured on the toy contextual bandit of ``tests/modules/test_q_ensemble.py`` (K=5, 300 steps, true Q = r):
held-out MSE of the mean 0.031 ("mean") vs 0.045 ("member"), from 4.8 at init; per-member MSE 1.37 vs 0.054;
member spread (std over k) on the data 1.06 vs 0.095 (0.08 at init: "mean" inflated it ~13x), off the data 4.6
vs 0.41. Both spreads grow off the data, but with "mean" the on-data spread is as large as the Q differences
the selector compares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from pe_rlhf.objectives.contract import KeyedLoss

from pe_rlhf.modules.q_ensemble import QEnsemble

__all__ = ["QEnsembleTDLoss", "REGRESSIONS"]

REGRESSIONS = ("mean", "member")


class QEnsembleTDLoss(KeyedLoss, LossModule):
    """TD loss of a :class:`~pe_rlhf.modules.QEnsemble` towards the value of the data's policy (module docstring).

    Args:
        qvalue_network: the ``QEnsemble`` to train. Its own parameters are the loss's ``qvalue_network_params``
            (the same tensors: an optimiser over either trains the ensemble in place).

    Keyword Args:
        gamma: discount in ``[0, 1]``.
        target_noise: ``sigma >= 0`` of the Gaussian noise on the target action (0: none, no random draw).
        regression: ``"mean"`` (the paper's: the members' mean is regressed) or ``"member"`` (each member).

    Target network: ``target_qvalue_network`` is a ``QEnsemble`` rebuilt from ``qvalue_network.config`` and
    loaded with its weights (building it draws a throwaway init from the global RNG, as the fit always has);
    its parameters are ``target_qvalue_network_params`` (no grad), which ``SoftUpdate(loss, tau=...)`` moves
    towards ``qvalue_network_params``. The target action's noise also draws from the global RNG.

    Default keys (``set_keys`` overrides): ``observation`` float ``(*B, obs_dim)`` (and
    ``("next", observation)``), ``action`` float ``(*B, A)`` in ``[-1, 1]``, ``next_action`` =
    ``("next", "action")`` float ``(*B, A)`` (a full key: the data's policy at ``s'``, written by
    ``add_next_actions``), ``reward`` float and ``terminated`` bool ``(*B, 1)`` (read under ``"next"``, as in
    TorchRL's losses). Any batch shape ``B`` (flattened); the input tensordict is read, never written.

    ``forward`` returns a TensorDict with batch size ``[]``: ``loss_qvalue`` (to minimise) and the detached
    diagnostics ``td_target`` (mean ``y``), ``q_value`` (mean of ``Q_k(s, a)`` over members and rows) and
    ``q_spread`` (mean over rows of the members' standard deviation, ``std_k Q_k(s, a)``, population form as
    the selector's ``variance_threshold`` reads it).
    """

    @dataclass
    class _AcceptedKeys:
        """Keys the loss reads (``set_keys`` renames them).

        Attributes:
            observation: ``"observation"``; the next observation is ``("next", observation)``.
            action: ``"action"``, the action taken at ``s``.
            next_action: ``("next", "action")``, the data's policy at ``s'`` (a full key).
            reward: ``"reward"``, read under ``"next"``.
            terminated: ``"terminated"``, read under ``"next"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        next_action: NestedKey = ("next", "action")
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    qvalue_network: QEnsemble
    target_qvalue_network: QEnsemble
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(self, qvalue_network: QEnsemble, *, gamma: float = 0.99, target_noise: float = 0.1,
                 regression: str = "mean") -> None:
        if not isinstance(qvalue_network, QEnsemble):
            raise TypeError(f"QEnsembleTDLoss expects a QEnsemble, got {type(qvalue_network).__name__}")
        if not (math.isfinite(gamma) and 0.0 <= gamma <= 1.0):
            raise ValueError(f"QEnsembleTDLoss gamma={gamma} is invalid: must be in [0, 1]")
        if not (math.isfinite(target_noise) and target_noise >= 0):
            raise ValueError(f"QEnsembleTDLoss target_noise={target_noise} is invalid: must be finite and >= 0")
        if regression not in REGRESSIONS:
            raise ValueError(f"QEnsembleTDLoss regression={regression!r} is invalid; allowed: {list(REGRESSIONS)}")
        super().__init__()
        self.gamma, self.target_noise, self.regression = float(gamma), float(target_noise), regression
        # A rebuilt copy rather than convert_to_functional's clone: its init's draws are part of the fit's seeded
        # stream (minibatches and noise come after them), so fits keep the numbers they had before this loss.
        target = QEnsemble(**qvalue_network.config)
        target.load_state_dict(qvalue_network.state_dict())
        target = target.to(next(qvalue_network.parameters()).device).requires_grad_(False)
        self.qvalue_network = qvalue_network
        self.target_qvalue_network = target
        # The members' stacked parameters, as convert_to_functional would name them: SoftUpdate pairs
        # target_<name>_params with <name>_params. Both are the networks' own TensorDictParams (same tensors).
        self.qvalue_network_params = qvalue_network.ensemble.params_td
        self.target_qvalue_network_params = target.ensemble.params_td
        self._has_update_associated["qvalue_network"] = False  # until a SoftUpdate is attached (torchrl warns)

    @staticmethod
    def read_keys(keys: QEnsembleTDLoss._AcceptedKeys) -> list[NestedKey]:
        """The keys a loss with ``tensor_keys == keys`` reads (its ``in_keys``), e.g. to check data before a fit."""
        return [keys.observation, keys.action, ("next", keys.observation), ("next", keys.reward),
                ("next", keys.terminated), keys.next_action]

    # the TorchRL contract (pe_rlhf.objectives.contract): in_keys, out_keys with setters, TD0 only
    def _loss_in_keys(self) -> list[NestedKey]:
        return self.read_keys(self.tensor_keys)

    def _loss_out_keys(self) -> list[str]:
        """``loss_qvalue`` and the diagnostics ``td_target``, ``q_value``, ``q_spread``."""
        return ["loss_qvalue", "td_target", "q_value", "q_spread"]

    def td_target(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``y`` per row ``(N,)`` of a flat batch, without gradient (draws the target-action noise)."""
        keys = self.tensor_keys
        observation = tensordict[keys.observation]
        n = observation.shape[0]
        next_td = tensordict["next"]
        reward = next_td[keys.reward].reshape(n).to(observation.dtype)
        terminated = next_td[keys.terminated].reshape(n).to(observation.dtype)
        with torch.no_grad():
            next_action = tensordict[keys.next_action]
            if self.target_noise > 0:
                next_action = next_action + self.target_noise * torch.randn_like(next_action)
            next_action = next_action.clamp(-1.0, 1.0)
            q_next = self.target_qvalue_network.values(next_td[keys.observation], next_action).mean(0)
            return reward + self.gamma * (1.0 - terminated) * q_next

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The TD loss on a batch of transitions (keys in the class docstring); see the class for the outputs.
        A missing key raises ``KeyError``."""
        tensordict = tensordict.reshape(-1)
        y = self.td_target(tensordict)
        q = self.qvalue_network.values(tensordict[self.tensor_keys.observation],
                                       tensordict[self.tensor_keys.action])  # (K, N)
        if self.regression == "mean":
            loss = (y - q.mean(0)).pow(2).mean()
        else:
            loss = (q - y).pow(2).mean()
        q = q.detach()
        return TensorDict({"loss_qvalue": loss, "td_target": y.mean(), "q_value": q.mean(),
                           "q_spread": q.std(0, unbiased=False).mean()}, batch_size=[])
