"""MLP critics evaluated from their stacked parameters, with the state's share of the work done once.

:class:`~pe_rlhf.objectives.PERLHFLoss` values one state at several actions (the executed action, the
agent's proposal on takeover rows, a fresh policy sample) with several critics (the twin proxy-Q, ``Q_int``,
optionally ``Q_dist``). A :class:`~pe_rlhf.modules.QValueNet` computes ``MLP(cat(s, a))``, whose first
layer is ``W [s; a] + b = W_s s + W_a a + b``. With an observation of 250 and 256 hidden units the state's
product ``W_s s`` is about half of a critic's forward work, and it does not depend on the action. So:

- :func:`project_state`: ``W_s s`` for every copy of a critic, once per state;
- :func:`evaluate`: the rest of the critic at chosen rows of that product and their actions,
  ``W_a a + b`` added, then the hidden and output layers as batched products over the copies.

The actor's path takes the product detached, so its backward computes only the 2 action columns of the
first layer's input gradient, not all 252. The values are those of the module itself up to the order of
the first layer's sum (``tests/objectives/test_fused_critics.py``).

:func:`mlp_plan` recognises the critics this applies to (``QValueNet`` of ``nn.Linear`` layers and
parameter-free activations); anything else goes through the module (``PERLHFLoss._q``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from pe_rlhf.modules.networks import QValueNet

Layers = list[tuple[torch.Tensor, torch.Tensor] | nn.Module]


@dataclass(frozen=True)
class MLPPlan:
    """How to read a critic's stacked parameters: its keys, its first layer's width ``obs + A``, and its layers
    in order (a ``(weight key, bias key)`` pair per linear layer, the module itself for an activation)."""

    observation_key: NestedKey
    action_key: NestedKey
    value_key: NestedKey
    in_features: int
    layers: tuple[tuple[tuple[str, ...], tuple[str, ...]] | nn.Module, ...]

    def read(self, params: TensorDictBase) -> Layers:
        """The layers with their ``(copies, out, in)`` weights and ``(copies, out)`` biases."""
        return [layer if isinstance(layer, nn.Module) else (params.get(layer[0]), params.get(layer[1]))
                for layer in self.layers]


def mlp_plan(critic: TensorDictModule) -> MLPPlan | None:
    """The plan of a ``make_qvalue`` critic (``QValueNet``: linear layers and parameter-free activations),
    or None for any other module."""
    net = getattr(critic, "module", None)
    if type(net) is not QValueNet or len(critic.in_keys) != 2 or len(critic.out_keys) != 1:
        return None
    layers: list = []
    for name, layer in net.mlp.named_children():
        if isinstance(layer, nn.Linear) and layer.bias is not None:
            layers.append((("module", "mlp", name, "weight"), ("module", "mlp", name, "bias")))
        elif isinstance(layer, (nn.ReLU, nn.Tanh, nn.ELU, nn.LeakyReLU, nn.SiLU, nn.GELU)):
            layers.append(layer)
        else:  # dropout, normalisation, ...: evaluate through the module
            return None
    if not layers or isinstance(layers[0], nn.Module) or isinstance(layers[-1], nn.Module):
        return None
    linear = [m for m in net.mlp.modules() if isinstance(m, nn.Linear)]
    if linear[-1].out_features != 1:
        return None
    observation_key, action_key = critic.in_keys
    return MLPPlan(observation_key, action_key, critic.out_keys[0], linear[0].in_features, tuple(layers))


def detached(layers: Layers) -> Layers:
    """The same layers with their parameters detached (the actor's path: no gradient to the critic)."""
    return [layer if isinstance(layer, nn.Module) else (layer[0].detach(), layer[1].detach()) for layer in layers]


def project_state(observation: torch.Tensor, layers: Layers) -> torch.Tensor:
    """``W_s s``, the observation's share of the first layer, for every copy: ``(copies, B, hidden)`` from a
    ``(B, obs)`` observation (no bias: :func:`evaluate` adds it)."""
    weight = layers[0][0]
    state_weight = weight[..., :observation.shape[-1]]  # (copies, hidden, obs)
    return torch.bmm(observation.expand(weight.shape[0], *observation.shape), state_weight.transpose(-1, -2))


def evaluate(layers: Layers, state_part: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``(copies, N)`` values from ``state_part`` ``(copies, N, hidden)`` (rows of :func:`project_state`)
    and ``action`` ``(N, A)``: the first layer's action columns and bias, then the remaining layers."""
    weight, bias = layers[0]
    action_weight = weight[..., weight.shape[-1] - action.shape[-1]:]  # (copies, hidden, A)
    h = torch.baddbmm(state_part + bias.unsqueeze(-2), action.expand(weight.shape[0], *action.shape),
                      action_weight.transpose(-1, -2))
    for layer in layers[1:]:
        if isinstance(layer, nn.Module):
            h = layer(h)
        else:
            h = torch.baddbmm(layer[1].unsqueeze(-2), h, layer[0].transpose(-1, -2))
    return h.squeeze(-1)
