"""The pieces of one PE-RLHF iteration: warm-up relabelling, one update, the batch's training metrics."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from pe_rlhf.objectives import PERLHFLoss


def relabel_warmup(batch: TensorDictBase) -> TensorDictBase:
    """Warm-up transitions as the loss should see them: the mentor's executed action stands as the
    agent's (so the CQL-style gap is 0) and no takeover is recorded (no intervention cost).

    Reads/writes ``action`` and, under ``next``: ``behavior_action``, ``intervention``,
    ``intervention_start``, ``intervention_cost`` (shapes ``(T, 2)`` / ``(T, 1)``).
    """
    batch = batch.clone(False)
    batch.set("action", batch.get(("next", "behavior_action")).clone())
    for key in ("intervention", "intervention_start"):
        batch.set(("next", key), torch.zeros_like(batch.get(("next", key))))
    batch.set(("next", "intervention_cost"), torch.zeros_like(batch.get(("next", "intervention_cost"))))
    return batch


def update(loss: PERLHFLoss, optimizers: dict, soft_update, sample: TensorDictBase,
           max_grad_norm: float | None) -> dict[str, float]:
    """One gradient step on every loss term, then the Polyak target update; returns detached scalars.

    Stops with a ``FloatingPointError`` naming the term if a loss is not finite (the caller saves a
    checkpoint first).
    """
    out = loss(sample)
    terms = {k: v for k, v in out.items() if k.startswith("loss_")}
    for name, value in terms.items():
        if not torch.isfinite(value):
            raise FloatingPointError(f"{name} is {value.item()} (not finite): updates stopped")
    for opt in optimizers.values():
        opt.zero_grad(set_to_none=True)
    sum(terms.values()).backward()
    for opt in optimizers.values():
        if max_grad_norm is not None:
            params = [p for group in opt.param_groups for p in group["params"]]
            torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
        opt.step()
    soft_update.step()
    return {k: float(v.detach()) for k, v in out.items()}


def batch_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Counts over one collected batch (flat ``(T,)``): steps, takeovers, starts, mentor chosen, cost."""
    nxt = batch.get("next")
    intervention = nxt.get("intervention").squeeze(-1)
    selected = nxt.get("mentor_selected").squeeze(-1) & intervention
    done = nxt.get("done").squeeze(-1)
    return {
        "steps": float(intervention.numel()),
        "takeover_steps": float(intervention.sum()),
        "takeover_starts": float(nxt.get("intervention_start").sum()),
        "mentor_chosen_steps": float(selected.sum()),
        "intervention_cost": float(nxt.get("intervention_cost").sum()),
        "safety_violations": float(nxt.get("cost").sum()),
        "episodes": float(done.sum()),
        "successes": float((nxt.get("success").squeeze(-1) & done).sum()),
    }
