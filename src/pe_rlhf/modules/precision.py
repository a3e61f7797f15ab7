"""Mixed precision for gradient updates: bf16 matrix products, fp32 weights, fp32 outputs.

``optim.precision=bf16`` (SAC-RS, SAC-Lag, PE-RLHF, HACO, HAIM-DRL) runs each update's loss forward
under ``torch.autocast(dtype=torch.bfloat16)``: the hidden layers' matrix products run in bf16 (CPUs
with AVX-512 BF16 or AMX, and GPUs, do them about twice as fast), while the weights, the optimiser
state and the gradients stay fp32. The networks' output layers are :class:`Float32Linear`, exempt
from autocast, so Q-values, the actor's ``loc``/``scale``, log-probabilities and every loss are
fp32: a Q of 90 in bf16 would be rounded to the nearest 0.5, coarser than the TD errors that train
it. Acting and evaluation stay fp32 (no autocast outside the update).

``benchmarks/sac_vs_sb3.py`` measures the speed; ``tests/modules/test_precision.py`` checks that bf16 updates
stay close to fp32 ones and still learn.
"""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F
from torch import nn

PRECISIONS = ("fp32", "bf16")


class Float32Linear(nn.Linear):
    """``nn.Linear`` that computes in fp32 even inside an autocast region (same parameters, same init).

    Input ``(..., in_features)`` of any float dtype, output ``(..., out_features)`` fp32. Outside
    autocast it equals ``nn.Linear`` exactly.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device_type=x.device.type, enabled=False):
            return F.linear(x.float(), self.weight, self.bias)


def fp32_output_layer(mlp: nn.Sequential) -> nn.Sequential:
    """Make ``mlp``'s last ``nn.Linear`` a :class:`Float32Linear` in place (no re-initialisation:
    the weights, their names and the RNG stream stay what they were); returns ``mlp``."""
    last = [m for m in mlp.modules() if type(m) is nn.Linear]
    if not last:
        raise ValueError(f"{type(mlp).__name__} has no nn.Linear layer to keep in fp32")
    last[-1].__class__ = Float32Linear
    return mlp


def update_precision(precision: str, device: torch.device | str = "cpu"):
    """Context for an update's loss forward: ``fp32`` does nothing, ``bf16`` autocasts to bfloat16."""
    if precision == "fp32":
        return contextlib.nullcontext()
    if precision == "bf16":
        return torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16)
    raise ValueError(f"precision={precision!r}: allowed {list(PRECISIONS)}")
