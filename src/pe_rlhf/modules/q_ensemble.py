"""The Q-ensemble estimator of PE-RLHF: K Q-networks evaluated in one vectorised call."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import EnsembleModule
from torch import nn

from pe_rlhf.modules.networks import make_qvalue


class QEnsemble(nn.Module):
    """K critics of the same architecture, independently initialised, run by ``vmap``.

    ``values(observation, action)`` takes ``(*B, obs_dim)`` and ``(*B, A)`` and returns
    ``(K, *B)``. As a tensordict module (``forward``) it reads ``observation`` and ``action``
    and writes ``state_action_value`` ``(K, *B, 1)`` with batch size ``(K, *B)``.
    """

    def __init__(self, obs_dim: int, action_dim: int = 2, num_members: int = 5,
                 hidden: tuple[int, ...] = (256, 256)):
        super().__init__()
        if num_members < 1:
            raise ValueError(f"QEnsemble num_members={num_members}: must be >= 1")
        self.num_members = num_members
        self.ensemble = EnsembleModule(make_qvalue(obs_dim, action_dim, hidden), num_copies=num_members)

    def forward(self, tensordict):
        return self.ensemble(tensordict)

    def values(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        batch = observation.shape[:-1]
        td = TensorDict({"observation": observation, "action": action}, batch_size=batch)
        return self.ensemble(td).get("state_action_value").squeeze(-1)
