"""The baselines' profiles: named sets of values composed over a recipe's ``config.yaml`` (Hydra's ``profile``
config group, as the PE-RLHF recipe's: :mod:`pe_rlhf.algorithms.proxy_q.config_profiles`).

``PROFILES[method]`` maps ``paper`` (the schema's values unchanged), ``cpu`` (PE-RLHF's budget) and ``smoke`` (CI,
seconds) to their values; ``profile=cpu`` on the command line selects one, and the ``key=value`` overrides apply
on top. :func:`pe_rlhf.algorithms.baselines.config.recipe_schema` registers a method's as the ``profile`` group.
"""

from __future__ import annotations

from typing import Any

PROFILE_NAMES = ("paper", "cpu", "smoke")

_SMOKE_ENV = {"horizon": 50, "min_blocks": 1, "max_blocks": 1}
_SMOKE_COMMON = {"env": _SMOKE_ENV, "eval": {"every_frames": 0, "episodes": 1}, "checkpoint": {"every_frames": 0}}
# PE-RLHF's budget (its cpu profile, the paper's 30K env steps): the baselines' curves where PE-RLHF is
# judged. On-policy runs collect whole batches, so theirs is 32K (8 x 4000, 4 x 8000). Algorithm
# hyper-parameters stay the paper's (8 PPO batches is what the budget buys, not a tuning choice).
# Measured on 2 busy cores (1 thread): env step ~4.5 ms; SAC-Lag update (256x256, batch 256) ~50 ms; a PPO
# minibatch of 100 ~21 ms. So SAC-* ~20 min, PPO-* ~5 min, CPO ~3 min, plus 3 evaluations of 20 episodes.
_EVAL_CPU = {"eval": {"every_frames": 10_000, "episodes": 20}, "checkpoint": {"every_frames": 10_000}}
_CPU = {"collector": {"total_frames": 30_000}, **_EVAL_CPU}
_CPU_ON_POLICY = {"collector": {"total_frames": 32_000}, **_EVAL_CPU}
_SAC = {
    "paper": {},
    "cpu": _CPU,
    "smoke": {**_SMOKE_COMMON,
              "collector": {"total_frames": 300, "frames_per_batch": 50, "learning_starts": 100},
              "replay_buffer": {"size": 1000, "batch_size": 32}, "optim": {"updates_per_batch": 50},
              "loss": {"hidden": [32, 32]}},
}
_PPO = {
    "paper": {},
    "cpu": _CPU_ON_POLICY,
    "smoke": {**_SMOKE_COMMON, "collector": {"total_frames": 300, "frames_per_batch": 100},
              "optim": {"epochs": 2, "minibatch_size": 50}, "loss": {"hidden": [32, 32]}},
}
_CPO = {
    "paper": {},
    "cpu": _CPU_ON_POLICY,
    "smoke": {**_SMOKE_COMMON, "collector": {"total_frames": 300, "frames_per_batch": 100},
              "optim": {"epochs": 2, "minibatch_size": 50}, "loss": {"hidden": [32, 32], "cg_iterations": 5}},
}

_SMOKE_DATA = {"steps": 200}
_SMOKE_OFFLINE = {"env": _SMOKE_ENV, "data": _SMOKE_DATA, "eval": {"every_updates": 0, "episodes": 1},
                  "checkpoint": {"every_updates": 0}}
_SMOKE_ONLINE = {"env": _SMOKE_ENV, "data": _SMOKE_DATA, "eval": {"every_frames": 0, "episodes": 1},
                 "checkpoint": {"every_frames": 0}}
# cpu: PE-RLHF's budget where there is interaction (30K env steps; 32K for GAIL's whole 4000-step PPO
# batches), 20 test episodes per evaluation, 20K demonstrations for BC/CQL/GAIL (HG-DAgger/IWR keep the
# paper's 30K: their warm-up is what makes them drive). Measured on 2 busy cores (1 thread, 256x256):
# professional recording ~250 steps/s; BC update (batch 32) ~4 ms; CQL update (batch 256) ~110 ms with 4
# random actions, ~250 ms with the default 10 (so cpu takes 4 and 15K updates); HG-DAgger/IWR env step
# (mentor + actor) ~8 ms, BC update (batch 256) ~6 ms. Estimates (recording included): BC ~7 min, CQL
# ~30 min, GAIL ~8 min, HG-DAgger/IWR ~10 min each.
_EVAL_CPU_UPDATES = {"eval": {"every_updates": 10_000, "episodes": 20}, "checkpoint": {"every_updates": 10_000}}
_EVAL_CPU_FRAMES = {"eval": {"every_frames": 10_000, "episodes": 20}, "checkpoint": {"every_frames": 10_000}}
_HIL = {
    "paper": {},
    "cpu": {"collector": {"total_frames": 30_000}, **_EVAL_CPU_FRAMES},
    "smoke": {**_SMOKE_ONLINE, "collector": {"total_frames": 300, "frames_per_batch": 100},
              "optim": {"batch_size": 32, "epochs": 2, "pretrain_epochs": 2}, "loss": {"hidden": [32, 32]}},
}

PROFILES: dict[str, dict[str, dict[str, Any]]] = {
    "sac_rs": _SAC,
    "sac_lag": _SAC,
    "ppo_rs": _PPO,
    "ppo_lag": _PPO,
    "cpo": _CPO,
    "bc": {
        "paper": {},
        "cpu": {"data": {"steps": 20_000}, "optim": {"updates": 50_000}, **_EVAL_CPU_UPDATES},
        "smoke": {**_SMOKE_OFFLINE, "optim": {"updates": 100, "updates_per_iteration": 25},
                  "loss": {"hidden": [32, 32]}},
    },
    "cql": {
        "paper": {},
        "cpu": {"data": {"steps": 20_000}, "optim": {"updates": 15_000}, "loss": {"bc_steps": 3_000, "num_random": 4},
                "eval": {"every_updates": 5_000, "episodes": 20}, "checkpoint": {"every_updates": 5_000}},
        "smoke": {**_SMOKE_OFFLINE, "optim": {"updates": 60, "updates_per_iteration": 20, "batch_size": 32},
                  "loss": {"bc_steps": 20, "num_random": 2, "hidden": [32, 32]}},
    },
    "gail": {
        "paper": {},
        "cpu": {"data": {"steps": 20_000}, "collector": {"total_frames": 32_000, "frames_per_batch": 4_000},
                **_EVAL_CPU_FRAMES},
        "smoke": {**_SMOKE_ONLINE, "collector": {"total_frames": 300, "frames_per_batch": 100},
                  "optim": {"epochs": 2, "minibatch_size": 50}, "loss": {"hidden": [32, 32]},
                  "discriminator": {"updates_per_batch": 20, "batch_size": 32, "hidden": [32, 32]}},
    },
    "hg_dagger": _HIL,
    "iwr": _HIL,
}

__all__ = ["PROFILES", "PROFILE_NAMES"]
