"""``fit_q_ensemble``: a few thousand Adam steps of :class:`~pe_rlhf.objectives.QEnsembleTDLoss` on warm-up data.

The loop a TorchRL script would write around the loss (sample, loss, backward, step, ``SoftUpdate``), with the
randomness fenced off: the fit seeds a forked RNG, so the same seed and data give the same ensemble and the
caller's RNG stream is left as it was.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import SoftUpdate

from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.objectives.q_ensemble_td import REGRESSIONS, QEnsembleTDLoss

__all__ = ["fit_q_ensemble"]


def _check_args(steps, batch_size, gamma, lr, target_noise, tau, loss):
    if not isinstance(steps, int) or steps < 0:
        raise ValueError(f"fit_q_ensemble: steps={steps!r} must be an int >= 0")
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"fit_q_ensemble: batch_size={batch_size!r} must be an int >= 1")
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"fit_q_ensemble: gamma={gamma} must be in [0, 1]")
    if not lr > 0:
        raise ValueError(f"fit_q_ensemble: lr={lr} must be > 0")
    if not target_noise >= 0:
        raise ValueError(f"fit_q_ensemble: target_noise={target_noise} must be >= 0")
    if not 0.0 < tau <= 1.0:
        raise ValueError(f"fit_q_ensemble: tau={tau} must be in (0, 1]")
    if loss not in REGRESSIONS:
        raise ValueError(f"fit_q_ensemble: loss={loss!r} must be 'mean' or 'member'")


def _sampler(data: Any, keys: Sequence[NestedKey], batch_size: int,
             device: torch.device) -> Callable[[], TensorDictBase]:
    """A function drawing a flat minibatch of ``keys`` from a TensorDict (uniform, with replacement) or a replay
    buffer (its own sampler); raises on data that lacks a key or holds nothing."""
    if isinstance(data, TensorDictBase):
        missing = [k for k in keys if k not in data.keys(include_nested=True)]
        if missing:
            raise KeyError(f"fit_q_ensemble: data lacks {missing} (has {sorted(map(str, data.keys(True, True)))}); "
                           "for recorded trajectories, add_next_actions(td) builds ('next', 'action')")
        flat = data.select(*keys).reshape(-1)
        if flat.numel() == 0:
            raise ValueError("fit_q_ensemble: data holds no transitions")
        flat = flat.to(device)
        return lambda: flat[torch.randint(flat.shape[0], (batch_size,), device=device)]
    if not hasattr(data, "sample"):
        raise TypeError(f"fit_q_ensemble: data must be a TensorDict or a replay buffer, got {type(data).__name__}")
    if hasattr(data, "__len__") and len(data) == 0:
        raise ValueError("fit_q_ensemble: the replay buffer is empty")

    def sample() -> TensorDictBase:
        batch = data.sample(batch_size)
        if not isinstance(batch, TensorDictBase):
            raise TypeError(f"fit_q_ensemble: the replay buffer returned {type(batch).__name__}, "
                            "expected a TensorDict")
        missing = [k for k in keys if k not in batch.keys(include_nested=True)]
        if missing:
            raise KeyError(f"fit_q_ensemble: replay-buffer samples lack {missing}")
        return batch.select(*keys).reshape(-1).to(device)

    return sample


def fit_q_ensemble(
    ensemble: QEnsemble,
    data: Any,
    *,
    steps: int,
    batch_size: int = 256,
    gamma: float = 0.99,
    lr: float = 3e-4,
    target_noise: float = 0.1,
    tau: float = 0.005,
    loss: str = "mean",
    next_action_key: NestedKey = ("next", "action"),
    seed: int = 0,
    progress: bool = False,
) -> dict[str, Any]:
    """Train ``ensemble`` in place for ``steps`` Adam steps of :class:`QEnsembleTDLoss` on ``data``.

    ``data`` is a TorchRL replay buffer (anything with ``sample(batch_size)`` returning a TensorDict) or a
    TensorDict of transitions (any batch shape; flattened) with the loss's default keys: ``observation``,
    ``action``, ``("next", "observation")``, ``("next", "reward")``, ``("next", "terminated")`` and the warm-up
    policy's action at ``s'`` under ``next_action_key`` (see ``pe_rlhf.modules.add_next_actions``). Each step
    draws a uniform minibatch of ``batch_size``, minimises ``QEnsembleTDLoss(gamma=, target_noise=,
    regression=loss)``'s ``loss_qvalue`` with Adam (``lr``) and moves the target copy with
    ``SoftUpdate(tau=tau)``.

    Randomness (the target copy's throwaway init, minibatches, noise) comes from ``torch.manual_seed(seed)``
    inside ``torch.random.fork_rng``, so the global RNG is left untouched; a replay buffer's own sampler draws
    from that same forked RNG. Works on a frozen (``requires_grad_(False)``) ensemble: the flags are turned on
    for the fit and restored afterwards. Replay-buffer priorities are not updated.

    Returns ``{"final_loss", "mean_loss", "first_loss", "steps", "loss", "loss_history"}`` (losses as floats,
    NaN when ``steps == 0``; ``loss_history`` a CPU tensor ``(steps,)``).
    """
    _check_args(steps, batch_size, gamma, lr, target_noise, tau, loss)
    if not isinstance(ensemble, QEnsemble):
        raise TypeError(f"fit_q_ensemble expects a QEnsemble, got {type(ensemble).__name__}")
    device = next(ensemble.parameters()).device
    keys = QEnsembleTDLoss.read_keys(QEnsembleTDLoss.default_keys(next_action=next_action_key))
    sample = _sampler(data, keys, batch_size, device)

    history = torch.zeros(steps, device=device)
    params = list(ensemble.parameters())
    flags = [p.requires_grad for p in params]
    fork_devices = [device] if device.type == "cuda" else []
    report_every = max(1, steps // 10)
    try:
        for p in params:
            p.requires_grad_(True)
        optim = torch.optim.Adam(ensemble.ensemble.params_td.parameters(), lr=lr)
        with torch.random.fork_rng(devices=fork_devices):
            torch.manual_seed(seed)
            loss_module = QEnsembleTDLoss(ensemble, gamma=gamma, target_noise=target_noise, regression=loss)
            loss_module.set_keys(next_action=next_action_key)
            with warnings.catch_warnings():  # torchrl's hint for eps = 1 - tau < 0.5 (tau is what is given here)
                warnings.filterwarnings("ignore", message="Found an eps value")
                target_updater = SoftUpdate(loss_module, tau=tau)
            for step in range(steps):
                value = loss_module(sample()).get("loss_qvalue")
                optim.zero_grad(set_to_none=True)
                value.backward()
                optim.step()
                target_updater.step()
                history[step] = value.detach()
                if progress and ((step + 1) % report_every == 0 or step + 1 == steps):
                    print(f"fit_q_ensemble: step {step + 1}/{steps} loss {value.item():.5f}", flush=True)
    finally:
        for p, flag in zip(params, flags):
            p.requires_grad_(flag)
    hist = history.cpu()
    nan = math.nan
    return {
        "final_loss": hist[-1].item() if steps else nan,
        "mean_loss": hist.mean().item() if steps else nan,
        "first_loss": hist[0].item() if steps else nan,
        "steps": steps,
        "loss": loss,
        "loss_history": hist,
    }
