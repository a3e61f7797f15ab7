"""Defaults, profiles and field rules of the imitation, offline and human-in-the-loop baselines.

:mod:`pe_rlhf.baselines.config` merges these into its tables (same loading, same errors). Families:

- ``offline`` (BC, CQL): gradient steps on recorded demonstrations, no env interaction; a metrics row
  every ``optim.updates_per_iteration`` updates, ``eval.every_updates`` / ``checkpoint.every_updates``.
- ``gail`` (GAIL): the PPO baselines' collector, optimiser and loss groups (the generator), a
  ``discriminator`` group and the demonstrations.
- ``hil`` (HG-DAgger, IWR): the simulated mentor (``mentor`` group, as the PE-RLHF recipe's) takes over
  the agent during collection; ``collector.frames_per_batch`` env steps a round, BC after each.

Every one of them reads ``data`` (:mod:`pe_rlhf.baselines.demos`): the demonstrations, recorded by the
recipe when missing. Values are the paper's appendix tables (BC, GAIL, HG-DAgger, IWR, SAC/CQL) where
they give one; the recipes' ``config.yaml`` names the others.
"""

from __future__ import annotations

import copy
from typing import Any

from omegaconf import DictConfig

from pe_rlhf.training.config_rules import (
    rule_choice,
    invalid_value,
    rule_hidden,
    rule_int,
    rule_mentor_name,
    rule_number,
    rule_optional,
    rule_string,
)

_DATA = {"path": None, "steps": 49_000, "mentor": "professional"}
_OFFLINE_PERIODS = {"eval": {"every_updates": 50_000, "episodes": 50, "split": "test"},
                    "checkpoint": {"every_updates": 50_000, "keep": 2}}
_PPO_LOSS = {"gamma": 0.99, "gae_lambda": 0.95, "clip_epsilon": 0.2, "kl_coef": 0.2, "kl_target": 0.01,
             "entropy_coef": 0.0, "critic_coef": 1.0, "normalize_advantage": False, "hidden": [256, 256]}
_HIL = {
    "mentor": {"name": "professional", "seed": 0, "kwargs": {}},
    "data": {**_DATA, "steps": 30_000},
    "collector": {"total_frames": 50_000, "frames_per_batch": 5_000},
    "optim": {"lr": 4.0e-4, "batch_size": 256, "epochs": 4, "pretrain_epochs": 50, "max_grad_norm": None},
    "loss": {"function": "nll", "hidden": [256, 256]},
    "eval": {"every_frames": 10_000, "episodes": 50, "split": "test"},
    "checkpoint": {"every_frames": 10_000, "keep": 2},
}
DEFAULTS: dict[str, dict[str, Any]] = {
    "bc": {
        "data": _DATA,
        "optim": {"updates": 200_000, "updates_per_iteration": 1_000, "batch_size": 32, "lr": 1.0e-4,
                  "max_grad_norm": None},
        "loss": {"function": "nll", "hidden": [256, 256]},
        **_OFFLINE_PERIODS,
    },
    "cql": {
        "data": _DATA,
        "optim": {"updates": 100_000, "updates_per_iteration": 1_000, "batch_size": 256, "lr": 1.0e-4,
                  "max_grad_norm": None},
        "loss": {"gamma": 0.99, "tau": 0.005, "temperature": 5.0, "min_q_weight": 0.2, "bc_steps": 20_000,
                 "num_random": 10, "target_entropy": "auto", "alpha_init": 1.0,
                 "hidden": [256, 256]},
        **_OFFLINE_PERIODS,
    },
    "gail": {
        "data": _DATA,
        "collector": {"total_frames": 1_000_000, "frames_per_batch": 12_800},
        "optim": {"lr": 1.0e-4, "epochs": 5, "minibatch_size": 64, "max_grad_norm": None},
        "loss": _PPO_LOSS,
        "discriminator": {"lr": 5.0e-3, "updates_per_batch": 2_000, "batch_size": 64, "hidden": [256, 256],
                          "grad_penalty": 0.0},
    },
    "hg_dagger": _HIL,
    "iwr": _HIL,
}

_SMOKE_ENV = {"horizon": 50, "min_blocks": 1, "max_blocks": 1}
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
_HIL_PROFILES = {
    "paper": {},
    "cpu": {"collector": {"total_frames": 30_000}, **_EVAL_CPU_FRAMES},
    "smoke": {**_SMOKE_ONLINE, "collector": {"total_frames": 300, "frames_per_batch": 100},
              "optim": {"batch_size": 32, "epochs": 2, "pretrain_epochs": 2}, "loss": {"hidden": [32, 32]}},
}
PROFILES: dict[str, dict[str, dict[str, Any]]] = {
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
    "hg_dagger": _HIL_PROFILES,
    "iwr": _HIL_PROFILES,
}


def defaults(method: str) -> dict[str, Any]:
    return copy.deepcopy(DEFAULTS[method])


def profiles(method: str) -> dict[str, dict[str, Any]]:
    return copy.deepcopy(PROFILES[method])


# --------------------------------------------------------------------------- field rules


def _demo_mentor(v) -> str | None:
    if v == "human":
        return "record a person's demonstrations first (pe-rlhf demo record --mentor human) and give data.path"
    return rule_mentor_name(v)


def _hil_mentor(v) -> str | None:
    if v == "human":
        return ("a person in the loop needs the PE-RLHF recipe's real-time pacing; here: a simulated mentor "
                "or a 'package.module:ClassName' import path")
    return rule_mentor_name(v)


def _mapping(v) -> str | None:
    return None if isinstance(v, (dict, DictConfig)) else "must be a mapping of SkillProfile fields"


RULES = {
    "data.path": rule_optional(rule_string), "data.steps": rule_int(1), "data.mentor": _demo_mentor,
    "mentor.name": _hil_mentor, "mentor.seed": rule_int(0), "mentor.kwargs": _mapping,
    "optim.updates": rule_int(1), "optim.updates_per_iteration": rule_int(1), "optim.batch_size": rule_int(1),
    "optim.pretrain_epochs": rule_int(0),
    "loss.function": rule_choice("nll", "mse"), "loss.temperature": rule_number(0, lo_open=True),
    "loss.min_q_weight": rule_number(0), "loss.bc_steps": rule_int(0), "loss.num_random": rule_int(1),
    "discriminator.lr": rule_number(0, lo_open=True), "discriminator.updates_per_batch": rule_int(1),
    "discriminator.batch_size": rule_int(1), "discriminator.hidden": rule_hidden, "discriminator.grad_penalty": rule_number(0),
    "eval.every_updates": rule_int(0), "checkpoint.every_updates": rule_int(0),
}
# The other fields (optim.lr, optim.epochs, the PPO and SAC loss fields, collector.*, eval.*, ...) mean what
# they mean for the RL baselines and use config.RULES.


def check_relations(cfg: DictConfig, family: str) -> None:
    """The fields of an imitation config that bound each other (ConfigError naming the first bad one)."""
    from pe_rlhf.training.config import check_mentor_kwargs

    data_steps = int(cfg.data.steps)
    o = cfg.optim
    if family == "offline":
        if o.batch_size > data_steps:
            raise invalid_value("optim.batch_size", o.batch_size, f"must be <= data.steps ({data_steps})")
        if o.updates_per_iteration > o.updates:
            raise invalid_value("optim.updates_per_iteration", o.updates_per_iteration,
                        f"must be <= optim.updates ({o.updates})")
    if family == "gail" and cfg.discriminator.batch_size > data_steps:
        raise invalid_value("discriminator.batch_size", cfg.discriminator.batch_size, f"must be <= data.steps ({data_steps})")
    if family == "hil":
        check_mentor_kwargs(cfg.mentor)
        if o.batch_size > data_steps:
            raise invalid_value("optim.batch_size", o.batch_size, f"must be <= data.steps ({data_steps}): the first "
                        "round fits on the demonstrations")
