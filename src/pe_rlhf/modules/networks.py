"""Actor and critic networks for the driving task (TorchRL modules with documented keys)."""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, Actor, ProbabilisticActor, TanhNormal

from pe_rlhf.modules.precision import fp32_output_layer


def _layer_norm_mlp(in_features: int, out_features: int, hidden: tuple[int, ...]) -> nn.Sequential:
    """Linear -> LayerNorm -> ReLU per hidden layer, then a linear output (RLPD's and BRO's critic)."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_features, width), nn.LayerNorm(width), nn.ReLU()]
        in_features = width
    return nn.Sequential(*layers, nn.Linear(in_features, out_features))


class QValueNet(nn.Module):
    """``Q(s, a)``: an MLP on ``cat(observation, action)`` returning ``(..., 1)``, always fp32 (its output
    layer is exempt from autocast: :mod:`pe_rlhf.modules.precision`). ``layer_norm``: a LayerNorm after each
    hidden layer, which keeps off-policy values from running away without conservatism (RLPD, BRO)."""

    def __init__(self, obs_dim: int, action_dim: int = 2, hidden: tuple[int, ...] = (256, 256),
                 layer_norm: bool = False):
        super().__init__()
        if layer_norm:
            mlp = _layer_norm_mlp(obs_dim + action_dim, 1, tuple(hidden))
        else:
            mlp = MLP(in_features=obs_dim + action_dim, out_features=1, num_cells=list(hidden),
                      activation_class=nn.ReLU)
        self.mlp = fp32_output_layer(mlp)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([observation, action], -1))


def make_qvalue(obs_dim: int, action_dim: int = 2, hidden: tuple[int, ...] = (256, 256),
                layer_norm: bool = False) -> TensorDictModule:
    """Critic module: reads ``observation`` ``(..., obs_dim)`` and ``action`` ``(..., A)``,
    writes ``state_action_value`` ``(..., 1)``; ``layer_norm`` as in :class:`QValueNet`."""
    return TensorDictModule(QValueNet(obs_dim, action_dim, hidden, layer_norm), in_keys=["observation", "action"],
                            out_keys=["state_action_value"])


class TanhHead(nn.Module):
    """``tanh(mlp(x))``: a bounded action (the MLP under ``mlp``, the name saved actors' weights carry)."""

    def __init__(self, mlp: nn.Module):
        super().__init__()
        self.mlp = mlp

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.mlp(observation))


def make_deterministic_actor(obs_dim: int, action_dim: int = 2, hidden: tuple[int, ...] = (256, 256)) -> Actor:
    """TD3-style actor: reads ``observation`` ``(..., obs_dim)``, writes ``action`` ``(..., A)`` in [-1, 1] (an MLP,
    then tanh). It explores only through what the collector adds (:class:`torchrl.modules.AdditiveGaussianModule`)."""
    mlp = fp32_output_layer(MLP(in_features=obs_dim, out_features=action_dim, num_cells=list(hidden),
                                activation_class=nn.ReLU))
    return Actor(TanhHead(mlp), in_keys=["observation"], out_keys=["action"],
                 spec=Bounded(-1.0, 1.0, (action_dim,)))


def make_actor(obs_dim: int, action_dim: int = 2, hidden: tuple[int, ...] = (256, 256)) -> ProbabilisticActor:
    """SAC-style actor: reads ``observation``, writes ``loc``, ``scale`` and ``action`` in [-1, 1]
    (TanhNormal); deterministic mode returns the distribution's mode. ``loc``/``scale`` are fp32 even
    under autocast (:mod:`pe_rlhf.modules.precision`)."""
    net = nn.Sequential(
        fp32_output_layer(MLP(in_features=obs_dim, out_features=2 * action_dim, num_cells=list(hidden),
                              activation_class=nn.ReLU)),
        NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
    )
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    spec = Bounded(-1.0, 1.0, (action_dim,))
    return ProbabilisticActor(module, in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
                              distribution_kwargs={"low": -1.0, "high": 1.0}, return_log_prob=False)
