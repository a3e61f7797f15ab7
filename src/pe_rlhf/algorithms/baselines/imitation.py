"""Imitation pieces shared by BC, GAIL, HG-DAgger and IWR: the BC loss, the takeover gate and weights,
the discriminator, minibatch epochs.

- :class:`WeightedBCLoss`: TorchRL's ``BCLoss`` with per-sample weights (IWR) and two fits: ``nll``
  (``-log pi(a|s)`` of the tanh-Gaussian actor, RLlib's BC) or ``mse`` (deterministic action vs label).
- :func:`hg_dagger_select`: HG-DAgger's gate, the steps of a collected batch the mentor drove, labelled
  with its action; :func:`executed_steps`: every step labelled with the executed action (IWR's data).
- :func:`iwr_weights`: IWR's re-weighting (Mandlekar et al. 2020), takeover and non-takeover samples
  carry equal total weight.
- :func:`make_discriminator` / :class:`DiscriminatorLoss` / :func:`gail_reward`: GAIL's ``D(s, a)`` on
  TorchRL's ``GAILLoss`` and the policy's reward ``-log(1 - D)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP
from torchrl.objectives import BCLoss, GAILLoss

from pe_rlhf.algorithms.baselines.algorithms import _NoTargets
from pe_rlhf.runtime.update import update
from pe_rlhf.transforms.keys import BEHAVIOR_ACTION, INTERVENTION

# A dataset row of the human-in-the-loop learners: the state, the label, whether the mentor drove.
DATASET_KEYS = ("observation", "action", INTERVENTION)


class WeightedBCLoss(BCLoss):
    """Behaviour cloning: TorchRL's ``BCLoss`` per sample, then ``mean_i(w_i * l_i)``.

    ``function="nll"``: ``l_i = -log pi(a_i|s_i)`` (TorchRL's BCLoss on a stochastic actor);
    ``"mse"``: ``l_i`` = mean over action dims of ``(a_det(s_i) - a_i)^2``, ``a_det`` the deterministic
    action (tanh of the Gaussian's mean). Reads ``observation`` (the actor's in_keys), ``action`` ``(N, A)``
    (the label) and, if present, ``weight`` ``(N,)`` (key set by ``set_keys(weight=...)``; absent: all 1).
    Writes ``loss_bc`` (scalar).
    """

    @dataclass
    class _AcceptedKeys(BCLoss._AcceptedKeys):
        weight: NestedKey = "weight"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network: TensorDictModule, function: str = "nll"):
        if function not in ("nll", "mse"):
            raise ValueError(f"WeightedBCLoss: function={function!r}; allowed: ['nll', 'mse']")
        super().__init__(actor_network, loss_function=None if function == "nll" else "l2", reduction="none")
        self.function = function

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        with set_exploration_type(ExplorationType.DETERMINISTIC):  # mse: the actor writes tanh(mean)
            per_sample = super().forward(tensordict).get("loss_bc")
        if per_sample.dim() > 1:
            per_sample = per_sample.mean(-1)
        weight = tensordict.get(self.tensor_keys.weight, None)
        loss = per_sample.mean() if weight is None else (per_sample * weight.reshape(per_sample.shape)).mean()
        return TensorDict({"loss_bc": loss})


def _takeover_flags(td: TensorDictBase) -> torch.Tensor:
    """``(N,)`` bool: ``("next", "intervention")`` of a collected step (whether the mentor drove it; the root
    ``intervention`` of a collected step is the previous step's), else ``intervention`` of a dataset row."""
    flags = td.get(("next", INTERVENTION), None)
    if flags is None:
        flags = td.get(INTERVENTION)
    return flags.reshape(-1).bool()


def hg_dagger_select(batch: TensorDictBase) -> TensorDictBase:
    """HG-DAgger's data: only the steps the mentor took over, labelled with its action.

    Reads (any batch shape, flattened): ``observation``, ``("next", "intervention")`` ``(..., 1)`` bool and
    ``("next", "behavior_action")`` ``(..., A)`` (what was executed: the mentor's action during a takeover,
    :class:`~pe_rlhf.transforms.InterventionTransform` without a selector). Returns ``(K,)`` rows of
    :data:`DATASET_KEYS`, ``K`` = the takeover steps, ``intervention`` all True.
    """
    flat = batch.reshape(-1)
    mask = _takeover_flags(flat)
    return TensorDict({"observation": flat.get("observation")[mask],
                       "action": flat.get(("next", BEHAVIOR_ACTION))[mask],
                       INTERVENTION: mask[mask].unsqueeze(-1)}, batch_size=[int(mask.sum())])


def executed_steps(batch: TensorDictBase) -> TensorDictBase:
    """IWR's data: every step, labelled with the executed action (the mentor's during a takeover, else the
    agent's own), with its takeover flag. Same keys and reads as :func:`hg_dagger_select`, ``(T,)`` rows."""
    flat = batch.reshape(-1)
    return TensorDict({"observation": flat.get("observation"), "action": flat.get(("next", BEHAVIOR_ACTION)),
                       INTERVENTION: _takeover_flags(flat).unsqueeze(-1)}, batch_size=[flat.numel()])


def demonstration_rows(demos: TensorDictBase) -> TensorDictBase:
    """Recorded demonstrations as dataset rows (:data:`DATASET_KEYS`): the mentor's action as the label,
    ``intervention`` False (whole demonstrations are not corrections of the agent)."""
    n = demos.numel()
    return TensorDict({"observation": demos.get("observation"), "action": demos.get("action"),
                       INTERVENTION: torch.zeros(n, 1, dtype=torch.bool)}, batch_size=[n])


def iwr_weights(data: TensorDictBase) -> torch.Tensor:
    """IWR's per-sample weights ``(N,)``: takeover samples ``N / (2 K)``, the others ``N / (2 (N - K))``, so
    each set carries half of the total weight ``N`` (mean weight 1). All or no takeovers: all 1.

    Reads ``("next", "intervention")`` (collected steps) or ``intervention`` (dataset rows).
    """
    flags = _takeover_flags(data)
    n, k = flags.numel(), int(flags.sum())
    if k in (0, n):
        return torch.ones(n)
    return torch.where(flags, torch.tensor(n / (2.0 * k)), torch.tensor(n / (2.0 * (n - k))))


def fit_epochs(loss, optimizers: dict, data: TensorDictBase, epochs: int, batch_size: int,
               max_grad_norm: float | None, weights: torch.Tensor | None = None) -> list[dict[str, float]]:
    """``epochs`` shuffled passes over ``data`` (flat) in minibatches of ``batch_size`` (the last one of a pass
    may be smaller), one :func:`~pe_rlhf.runtime.update.update` each; ``weights`` ``(N,)`` go to the
    loss as ``weight``. Returns each update's scalars."""
    if weights is not None:
        data = data.clone(False)
        data.set("weight", weights)
    n, outputs = data.numel(), []
    for _ in range(epochs):
        order = torch.randperm(n)
        for start in range(0, n, batch_size):
            outputs.append(update(loss, optimizers, _NO_TARGETS, data[order[start:start + batch_size]], max_grad_norm))
    return outputs


_NO_TARGETS = _NoTargets()


# --------------------------------------------------------------------------- GAIL


class Discriminator(nn.Module):
    """``D(s, a) = sigmoid(MLP(cat(s, a)))``: the probability that ``(s, a)`` is the mentor's."""

    def __init__(self, obs_dim: int, action_dim: int, hidden):
        super().__init__()
        self.mlp = MLP(in_features=obs_dim + action_dim, out_features=1, num_cells=list(hidden),
                       activation_class=nn.ReLU)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.mlp(torch.cat([observation, action], -1)))


def make_discriminator(obs_dim: int, hidden, action_dim: int = 2) -> TensorDictModule:
    """Reads ``observation``, ``action``; writes ``d_prob`` ``(..., 1)`` in (0, 1)."""
    return TensorDictModule(Discriminator(obs_dim, action_dim, hidden), in_keys=["observation", "action"],
                            out_keys=["d_prob"])


class DiscriminatorLoss(GAILLoss):
    """TorchRL's ``GAILLoss`` (binary cross-entropy: demonstrations 1, the policy's steps 0, optional gradient
    penalty) with its output named like every other loss here: ``loss_discriminator`` (and ``gp_loss``).

    Reads ``observation``/``action`` (demonstrations) and ``collector_observation``/``collector_action``
    (the policy's), ``(B, ...)`` each; the discriminator's ``d_prob``.
    """

    def __init__(self, discriminator: TensorDictModule, grad_penalty: float = 0.0):
        super().__init__(discriminator, use_grad_penalty=grad_penalty > 0, gp_lambda=grad_penalty)
        self.set_keys(discriminator_pred="d_prob")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = super().forward(tensordict)
        renamed = TensorDict({"loss_discriminator": out.get("loss")})
        if "gp_loss" in out.keys():  # noqa: SIM118 - a TensorDict: `in` on it would test a tensor
            renamed.set("gp_loss", out.get("gp_loss"))
        return renamed


@torch.no_grad()
def gail_reward(discriminator: TensorDictModule, data: TensorDictBase, eps: float = 1e-6) -> torch.Tensor:
    """The policy's reward ``-log(1 - D(s, a))`` ``(..., 1)``: high where the discriminator takes the
    step for the mentor's. Reads ``observation``, ``action``."""
    d = discriminator(data.select("observation", "action")).get("d_prob")
    return -torch.log((1.0 - d).clamp_min(eps))
