"""One gradient step of any method's TorchRL loss: every ``loss_*`` term, per-optimizer clipping, the target update.

The learners of every method call :func:`update` on each replay (or demonstration) sample: the proxy-Q learner
(:mod:`pe_rlhf.algorithms.proxy_q`) and the baselines (:mod:`pe_rlhf.algorithms.baselines`). A non-finite loss term,
gradient norm or parameter stops the run with a ``FloatingPointError`` that names it (:func:`nonfinite_parameters`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule

from pe_rlhf.modules.precision import update_precision


def update(loss: LossModule, optimizers: dict, soft_update, sample: TensorDictBase,
           max_grad_norm: float | None, precision: str = "fp32") -> dict[str, float]:
    """One gradient step on every loss term, then the Polyak target update; returns detached scalars.

    ``precision="bf16"`` runs the loss forward under bf16 autocast (the backward follows it; weights,
    gradients and optimiser state stay fp32): :mod:`pe_rlhf.modules.precision`.

    Stops with a ``FloatingPointError`` before any parameter changes if a loss term (named) or an
    optimizer's gradient norm (optimizer named) is not finite, and after the step if a parameter
    (named) became non-finite anyway. The run saves a checkpoint before it passes the error on
    (:class:`~pe_rlhf.runtime.run.Run`).
    """
    with update_precision(precision, sample.device or "cpu"):
        out = loss(sample)
    terms = {k: v for k, v in out.items() if k.startswith("loss_")}
    for name, value in terms.items():
        if not torch.isfinite(value):
            raise FloatingPointError(f"{name} is {value.item()} (not finite): updates stopped")
    for opt in optimizers.values():
        opt.zero_grad(set_to_none=True)
    sum(terms.values()).backward()
    for name, opt in optimizers.items():  # every norm before any step: a bad gradient changes nothing
        params = [p for group in opt.param_groups for p in group["params"] if p.grad is not None]
        norm = torch.nn.utils.clip_grad_norm_(params, max_grad_norm if max_grad_norm is not None else float("inf"))
        if not torch.isfinite(norm):
            raise FloatingPointError(f"the gradient of optimizer {name!r} has norm {norm.item()} (not finite): "
                                     "updates stopped before the step")
    for opt in optimizers.values():
        opt.step()
    soft_update.step()
    bad = nonfinite_parameters(loss)
    if bad:
        raise FloatingPointError(f"parameters {bad[:5]} became non-finite after an update: updates stopped")
    return {k: float(v.detach()) for k, v in out.items()}


def nonfinite_parameters(module: torch.nn.Module) -> list[str]:
    """Names of ``module``'s parameters holding NaN or inf (one fused check when none do; target
    networks are Polyak averages of these, finite while they are)."""
    params = dict(module.named_parameters())
    if not params or bool(torch.isfinite(torch.stack([p.detach().sum() for p in params.values()])).all()):
        return []
    return [name for name, p in params.items() if not torch.isfinite(p.detach()).all()]
