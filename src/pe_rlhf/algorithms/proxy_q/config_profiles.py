"""The recipe's profiles: named sets of values composed over a recipe's ``config.yaml`` (a Hydra config group).

``profile=cpu`` on the command line selects one (a recipe's ``config.yaml`` names its own in its ``defaults`` list,
``profile: paper``); its values replace the file's, and the command line's ``key=value`` overrides apply on top.
:func:`pe_rlhf.runtime.config_compose.store_recipe_configs` registers each as ``profile/<name>``.
"""

from __future__ import annotations

from typing import Any

PROFILES: dict[str, dict[str, Any]] = {
    # The paper's appendix values: the schema's defaults unchanged (pe_rlhf.algorithms.proxy_q.config_schema).
    "paper": {},
    # A 30K-step run on 2 CPU cores in well under 45 min. Measured here (2 cores, obs 250, 256x256):
    # a PERLHFLoss update costs 56 ms at batch 1024 and 25 ms at batch 256; a PE-RLHF env step (mentor,
    # IDM-MOBIL, 5-member selector, actor) 16 ms; an ensemble fit step 47 ms. The paper's 30K updates
    # at batch 1024 alone take ~28 min, ~50 min with the env and 6 evaluations of 10 episodes (up to
    # 60K extra env steps) plus video. So: batch 256 (updates ~12.5 min) keeping the paper's
    # update-to-data ratio (100 updates per 100 env steps) and its 256x256 networks, since the UTD
    # ratio and the function class matter more to sample efficiency than the batch (256 is SAC's usual
    # batch); evaluation 20 episodes every 10K steps without video (5 misled: test scenes 1000-1004 are easy).
    # Estimate: ~12.5 (updates) + ~8 (30K env steps) + ~3 (eval) + ~1.5 (2000 fit steps) = ~25 min.
    "cpu": {
        "replay_buffer": {"batch_size": 256},
        "optim": {"updates_per_batch": 100},
        "eval": {"every_frames": 10000, "episodes": 20, "video": False},  # 5 read 0.4-0.8 on easy scenes
        "checkpoint": {"every_frames": 10000},
    },
    # `make run`: the cpu profile on a ~10-minute budget (9K env steps, 5K of them warm-up), one
    # evaluation of 10 test episodes at the end, a GIF; `train.py --compare idm-mobil` adds the
    # physics policy on the same scenes to the final table.
    # The recipe's batch (128, PE-RLHF's) stays; no actor picking (its evaluations would not fit the budget).
    "quick": {
        "collector": {"total_frames": 9000, "warmup_steps": 5000},
        "eval": {"every_frames": 0, "episodes": 10, "video": True},
        "checkpoint": {"every_frames": 3000},
        "actor_selection": {"every_frames": 0},
    },
    # CI: the whole loop (warm-up, updates, eval, checkpoint) in about a minute. No test-episode GIF:
    # filming it was ~45% of a smoke run's CPU time (cProfile, 2026-12-06); eval.video=true films it.
    "smoke": {
        "env": {"horizon": 100, "min_blocks": 2, "max_blocks": 2},
        "collector": {"total_frames": 300, "frames_per_batch": 50, "warmup_steps": 100},
        "replay_buffer": {"size": 1000, "batch_size": 32},
        "optim": {"updates_per_batch": 5},
        "loss": {"hidden": [32, 32]},
        "eval": {"every_frames": 300, "episodes": 1, "video": False},
        "checkpoint": {"every_frames": 300, "keep": 1},
        "actor_selection": {"every_frames": 0},
    },
}

