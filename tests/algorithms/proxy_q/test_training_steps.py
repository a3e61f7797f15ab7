"""The pieces of one training iteration (pe_rlhf.algorithms.proxy_q.steps) on plain TensorDicts."""

import torch
from tensordict import TensorDict

from pe_rlhf.algorithms.proxy_q.steps import batch_metrics, ensemble_transitions, relabel_warmup


def _batch(t=6, done_at=(2,)):
    """A flat (T,) collected batch in the intervention transform's layout, warm-up style."""
    agent = torch.arange(t * 2, dtype=torch.float32).reshape(t, 2) / 100  # the agent's proposals
    mentor = -torch.arange(t * 2, dtype=torch.float32).reshape(t, 2) / 10  # executed by the mentor
    done = torch.zeros(t, 1, dtype=torch.bool)
    done[list(done_at)] = True
    start = torch.zeros(t, 1, dtype=torch.bool)
    start[0] = True
    return TensorDict({
        "observation": torch.randn(t, 4),
        "action": agent,
        "next": {
            "observation": torch.randn(t, 4),
            "behavior_action": mentor,
            "mentor_action": mentor.clone(),
            "intervention": torch.ones(t, 1, dtype=torch.bool),
            "intervention_start": start,
            "intervention_cost": start.float() * 0.7,
            "mentor_selected": torch.ones(t, 1, dtype=torch.bool),
            "reward": torch.ones(t, 1),
            "cost": torch.zeros(t, 1),
            "success": done.clone(),
            "done": done,
            "terminated": done.clone(),
        },
    }, [t])


def test_ensemble_transitions_fit_the_executed_action_and_its_successor():
    batch = _batch()
    td = ensemble_transitions(batch)
    executed = batch["next", "behavior_action"]
    assert torch.equal(td["action"], executed)  # the mentor's action, never the agent's proposal
    # next action = the executed action one step later, except across the episode end (step 2) and at the end
    assert torch.equal(td["next", "action"][0], executed[1])
    assert torch.equal(td["next", "action"][2], executed[2])
    assert torch.equal(td["next", "action"][3], executed[4])
    assert torch.equal(td["next", "action"][-1], executed[-1])
    assert torch.equal(batch["action"], _batch()["action"])  # the input is not modified


def test_relabel_warmup_keeps_the_agent_proposals_as_takeovers_without_charging_them():
    batch = _batch()
    out = relabel_warmup(batch)
    assert torch.equal(out["action"], batch["action"])
    assert out["next", "intervention"].all()
    assert not out["next", "intervention_start"].any()
    assert out["next", "intervention_cost"].abs().sum() == 0
    assert batch["next", "intervention_start"].any()  # the input is not modified


def test_batch_metrics_counts():
    m = batch_metrics(_batch(t=6, done_at=(2, 5)))
    assert m["steps"] == 6 and m["takeover_steps"] == 6 and m["takeover_starts"] == 1
    assert m["mentor_chosen_steps"] == 6 and m["episodes"] == 2 and m["successes"] == 2
    assert abs(m["intervention_cost"] - 0.7) < 1e-6


def test_batch_metrics_sum_the_disturbance_cost_only_when_the_batch_has_it():
    batch = _batch(t=6)
    assert "disturbance_cost" not in batch_metrics(batch)  # PE-RLHF / HACO: no such column
    cost = torch.zeros(6, 1)
    cost[1], cost[4] = 0.25, 0.5
    batch.set(("next", "disturbance_cost"), cost)
    assert abs(batch_metrics(batch)["disturbance_cost"] - 0.75) < 1e-6
