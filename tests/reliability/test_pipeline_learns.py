"""Issue 45, case 10: the assembled pipeline learns: the takeover rate falls on a fixed scene.

The recipe (``recipes/pe_rlhf/train.py``) as it ships (a simulated mentor, physics and the hybrid selector inside
``InterventionTransform``) with proxy values (``loss.objective=proxy_value``: PVP's labels, TD and behaviour cloning
on takeover rows), on one straight road without traffic or obstacles. The starting policy is made clearly bad in a
controlled way: the actor's output layer is set so that it steers hard to one side whatever it sees, which the mentor's
danger check takes over. No warm-up: the first batch is collected before any update (updates start once a batch is
in), so it measures the bad policy; the updates that follow must bring the takeover rate of the last three batches
well below it.

Before: no test showed the assembled pipeline learning (a previous attempt at smoke scale found nothing to fall:
with a warm-up the proxy values had already learned, without one the untrained actor was rarely taken over).
"""

from __future__ import annotations

import csv

import pytest
import torch
from _runs import load_recipe

from pe_rlhf.algorithms.proxy_q import builders

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning"),
              pytest.mark.filterwarnings("ignore::FutureWarning")]

FRAMES, BATCH = 600, 50
SETTINGS = ["profile=smoke", "optim.device=cpu", "seed=0", "loss.objective=proxy_value", "loss.bc_weight=1.0",
            "env.block_types=[straight]", "env.traffic_density=0", "env.obstacle_density=0", "env.horizon=100",
            f"collector.total_frames={FRAMES}", f"collector.frames_per_batch={BATCH}",
            "collector.warmup_steps=0",
            "optim.updates_per_batch=40", "optim.lr=0.003", "eval.every_frames=0", "eval.episodes=1",
            "eval.video=false", "checkpoint.every_frames=0"]


def steering_hard(build):
    """``build_actor``, its output layer set so that the action is about (steering 0.76, throttle 0.46) at any state."""

    def build_actor(cfg):
        actor = build(cfg)
        last = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)][-1]
        with torch.no_grad():
            last.weight.mul_(0.01)
            last.bias.copy_(torch.tensor([1.0, 0.5]))
        return actor

    return build_actor


def test_the_takeover_rate_falls_as_the_pipeline_learns(tmp_path, monkeypatch):
    monkeypatch.setattr(builders, "build_actor", steering_hard(builders.build_actor))
    load_recipe().main([*SETTINGS, "--out", str(tmp_path)])
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    rates = [float(r["train/takeover_rate"]) for r in rows]
    assert [int(float(r["env_steps"])) for r in rows] == list(range(BATCH, FRAMES + 1, BATCH))
    first, last = rates[0], sum(rates[-3:]) / 3  # rates[0]: the bad policy, collected before any update
    assert first > 0.9 and last < 0.5 * first, rates
