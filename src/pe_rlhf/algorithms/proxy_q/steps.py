"""The pieces of one PE-RLHF iteration: warm-up relabelling, the ensemble's transitions, the batch's training metrics
(the gradient step itself is every method's: :func:`pe_rlhf.runtime.update.update`)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from pe_rlhf.modules import add_next_actions
from pe_rlhf.transforms.keys import (BEHAVIOR_ACTION, INTERVENTION, INTERVENTION_COST, INTERVENTION_START,
                                     MENTOR_SELECTED)


def ensemble_transitions(batch: TensorDictBase) -> TensorDictBase:
    """Transitions as the Q-ensemble is fitted on them (the warm-up's): a copy whose ``action`` is the executed
    (mentor's) ``("next", "behavior_action")`` and whose ``("next", "action")`` is the action executed
    at ``s'`` (:func:`~pe_rlhf.modules.add_next_actions`), so ``Q_k`` estimates the value of the
    *driving* policy. (The root ``action`` of a collected batch is the agent's proposal, which the
    mentor overrode during warm-up: fitted on it, ``Q`` would learn that the action does not matter.)

    ``batch``: a flat ``(T,)`` run of consecutive steps from the collector.
    """
    td = batch.select("observation", "next", strict=False).clone()
    td.set("action", td.get(("next", BEHAVIOR_ACTION)).clone())
    return add_next_actions(td)


def relabel_warmup(batch: TensorDictBase) -> TensorDictBase:
    """Warm-up transitions as the loss should see them. The mentor (or the warm-up policy) drove every
    step, so nothing is charged: ``intervention_start`` and ``intervention_cost`` are zeroed (forced
    driving is no takeover).

    The agent's proposals stay as ``action`` and every step stays flagged ``intervention``, so the
    CQL-style gap ranks the mentor's action above the agent's from the first update (the paper's warm-up,
    in which "human mentors continuously control the agent"). (Letting the mentor's action stand as the
    agent's, gap 0, was an option until its measurement lost: docs/experiments/first-30k-runs.md.)

    Reads/writes ``action`` and, under ``next``: ``behavior_action``, ``intervention``,
    ``intervention_start``, ``intervention_cost`` (shapes ``(T, 2)`` / ``(T, 1)``).
    """
    batch = batch.clone(False)
    nxt = batch.get("next")
    nxt.set(INTERVENTION, torch.ones_like(nxt.get(INTERVENTION)))
    nxt.set(INTERVENTION_START, torch.zeros_like(nxt.get(INTERVENTION_START)))
    nxt.set(INTERVENTION_COST, torch.zeros_like(nxt.get(INTERVENTION_COST)))
    return batch


def batch_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Counts over one collected batch (flat ``(T,)``): steps, takeovers, starts, mentor chosen, cost,
    episodes ended by a simulator fault (``sim_error``); ``disturbance_cost`` (sum) only when the batch
    has HAIM-DRL's ``("next", "disturbance_cost")``."""
    nxt = batch.get("next")
    sim_error = nxt.get("sim_error", None)
    intervention = nxt.get(INTERVENTION).squeeze(-1)
    selected = nxt.get(MENTOR_SELECTED).squeeze(-1) & intervention
    done = nxt.get("done").squeeze(-1)
    disturbance = nxt.get("disturbance_cost", None)
    return {
        **({"disturbance_cost": float(disturbance.sum())} if disturbance is not None else {}),
        "steps": float(intervention.numel()),
        "takeover_steps": float(intervention.sum()),
        "takeover_starts": float(nxt.get(INTERVENTION_START).sum()),
        "mentor_chosen_steps": float(selected.sum()),
        "intervention_cost": float(nxt.get(INTERVENTION_COST).sum()),
        "safety_violations": float(nxt.get("cost").sum()),
        "episodes": float(done.sum()),
        "successes": float((nxt.get("success").squeeze(-1) & done).sum()),
        "sim_errors": float(sim_error.sum()) if sim_error is not None else 0.0,
    }
