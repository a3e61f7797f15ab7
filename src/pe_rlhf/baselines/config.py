"""The RL and safe-RL baselines' configuration: per-method defaults, profiles, field rules, loading.

``load_baseline_config(method, path, overrides)`` layers, each on top of the one before (as
:func:`pe_rlhf.training.config.load_config` does for PE-RLHF, whose merging, override parsing, env check
and errors it reuses):

1. :func:`default_config` of ``method`` (the paper's values; a copy of ``recipes/<method>/config.yaml``,
   kept equal by a test),
2. the YAML file (``path``, or ``recipes/<method>/config.yaml`` when found; may be partial),
3. the profile's overrides (:func:`profiles`; ``profile`` from the overrides, else from the file),
4. the dotlist overrides (``["optim.lr=3e-4", "constraint.cost_limit=0"]``),

then :func:`validate_baseline_config`. Every group is closed (an unknown key fails naming it) except
``env`` (any :class:`~pe_rlhf.envs.config.DrivingConfig` field). Errors are
:class:`~pe_rlhf.training.config.ConfigError` naming the dotted field, the value and what is allowed.

Methods (:data:`METHODS`): ``sac_rs``, ``sac_lag`` (off-policy family ``sac``), ``ppo_rs``, ``ppo_lag``
(family ``ppo``) and ``cpo``. "RS" is the env's shaped reward (spec §4) as it is; ``*_lag`` and ``cpo`` add
the constraint ``mean episode cost <= constraint.cost_limit`` on the env's ``("next", "cost")``. The
imitation baselines ``bc``, ``cql`` (family ``offline``), ``gail`` and ``hg_dagger``, ``iwr`` (family ``hil``,
with a mentor in the loop) take their defaults, profiles and extra rules from
:mod:`~pe_rlhf.baselines.imitation_config`; ``mentor.kwargs`` is open as in the PE-RLHF recipe.

The paper's cost limit is 1 per episode, for MetaDrive's safe env, where an episode goes on after a
collision and costs pile up. Here an episode ends at its first collision (:mod:`pe_rlhf.envs.driving_env`),
so an episode costs 0 or 1 and ``J_c <= 1`` always: with the limit 1, ``lambda`` never rises and CPO's
constraint is never violated (at best ``c = 0``). ``constraint.cost_limit`` below 1 is then the crash rate
allowed per episode (e.g. 0.2).
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from pe_rlhf.baselines import imitation_config
from pe_rlhf.modules.precision import PRECISIONS
from pe_rlhf.training.config import (
    RECIPES_ENV_VAR,
    check_env,
    check_key,
    check_recorded_algorithm,
    leaf_keys,
    merge_values,
    parse_overrides,
    read_config_file,
)
from pe_rlhf.training.config_rules import (
    SPLITS,
    WANDB_MODES,
    ConfigError,
    invalid_value,
    rule_bool,
    rule_choice,
    rule_hidden,
    rule_int,
    rule_number,
    rule_optional,
    rule_string,
    rule_target_entropy,
)


@dataclass(frozen=True)
class Method:
    """A baseline: its display name, its family (``sac``: off-policy, ``ppo``/``cpo``: on-policy) and
    whether it has a Lagrange multiplier."""

    name: str
    family: str
    lagrangian: bool


METHODS: dict[str, Method] = {
    "sac_rs": Method("SAC-RS", "sac", False),
    "sac_lag": Method("SAC-Lag", "sac", True),
    "ppo_rs": Method("PPO-RS", "ppo", False),
    "ppo_lag": Method("PPO-Lag", "ppo", True),
    "cpo": Method("CPO", "cpo", False),
    # imitation, offline and human-in-the-loop (pe_rlhf.baselines.imitation_config)
    "bc": Method("BC", "offline", False),
    "cql": Method("CQL", "offline", False),
    "gail": Method("GAIL", "gail", False),
    "hg_dagger": Method("HG-DAgger", "hil", False),
    "iwr": Method("IWR", "hil", False),
}
IMITATION_FAMILIES = ("offline", "gail", "hil")

# The paper's appendix tables (SAC/SAC-Lag, PPO/PPO-Lag, CPO) where they give a value; every other
# value is named "not in the paper" in the recipes' config.yaml, with where it comes from.
_COMMON: dict[str, Any] = {
    "seed": 0,
    "profile": "paper",
    "env": {"lane_features": True},
    "logger": {"out_dir": None, "csv": True, "wandb": False, "wandb_mode": "offline", "wandb_project": "pe-rlhf",
               "tensorboard": False, "mlflow": False, "log_every": 1},
    "eval": {"every_frames": 100_000, "episodes": 50, "split": "test"},
    "checkpoint": {"every_frames": 50_000, "keep": 2},
}
_FAMILY: dict[str, dict[str, Any]] = {
    "sac": {
        "collector": {"total_frames": 1_000_000, "frames_per_batch": 100, "learning_starts": 10_000,
                      "init_random_frames": 0},
        "replay_buffer": {"size": 1_000_000, "batch_size": 256},
        "optim": {"lr": 1.0e-4, "updates_per_batch": 100, "max_grad_norm": None, "precision": "fp32"},
        "loss": {"gamma": 0.99, "tau": 0.005, "num_qvalue_nets": 2, "target_entropy": "auto", "alpha_init": 1.0,
                 "hidden": [256, 256], "deactivate_vmap": True},
    },
    "ppo": {
        "collector": {"total_frames": 1_000_000, "frames_per_batch": 4000},
        "optim": {"lr": 5.0e-5, "epochs": 20, "minibatch_size": 100, "max_grad_norm": None},
        "loss": {"gamma": 0.99, "gae_lambda": 0.95, "clip_epsilon": 0.2, "kl_coef": 0.2, "kl_target": 0.01,
                 "entropy_coef": 0.0, "critic_coef": 1.0, "normalize_advantage": False, "hidden": [256, 256]},
    },
    "cpo": {
        "collector": {"total_frames": 1_000_000, "frames_per_batch": 8000},
        "optim": {"lr": 5.0e-5, "epochs": 20, "minibatch_size": 100, "max_grad_norm": None},
        "loss": {"gamma": 0.99, "gae_lambda": 0.95, "target_kl": 0.01, "cg_iterations": 10, "cg_damping": 0.1,
                 "backtrack_ratio": 0.8, "max_backtracks": 15, "hidden": [256, 256]},
        "constraint": {"cost_limit": 1.0, "window": 10},
    },
}
_LAGRANGIAN: dict[str, dict[str, Any]] = {  # the constraint group of the *_lag methods
    "sac": {"cost_limit": 1.0, "window": 20, "lambda_lr": 0.01, "lambda_init": 0.0},
    "ppo": {"cost_limit": 1.0, "window": 10, "lambda_lr": 0.05, "lambda_init": 0.0},
}
_SAC_LAG_LOSS = {"num_cost_qvalue_nets": 2, "cost_aggregate": "max"}

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
_PROFILES: dict[str, dict[str, dict[str, Any]]] = {
    "sac": {
        "paper": {},
        "cpu": _CPU,
        "smoke": {**_SMOKE_COMMON,
                  "collector": {"total_frames": 300, "frames_per_batch": 50, "learning_starts": 100},
                  "replay_buffer": {"size": 1000, "batch_size": 32}, "optim": {"updates_per_batch": 50},
                  "loss": {"hidden": [32, 32]}},
    },
    "ppo": {
        "paper": {},
        "cpu": _CPU_ON_POLICY,
        "smoke": {**_SMOKE_COMMON, "collector": {"total_frames": 300, "frames_per_batch": 100},
                  "optim": {"epochs": 2, "minibatch_size": 50}, "loss": {"hidden": [32, 32]}},
    },
    "cpo": {
        "paper": {},
        "cpu": _CPU_ON_POLICY,
        "smoke": {**_SMOKE_COMMON, "collector": {"total_frames": 300, "frames_per_batch": 100},
                  "optim": {"epochs": 2, "minibatch_size": 50}, "loss": {"hidden": [32, 32], "cg_iterations": 5}},
    },
}
PROFILE_NAMES = ("paper", "cpu", "smoke")


def _method(method: str) -> Method:
    if method not in METHODS:
        raise invalid_value("method", method, f"allowed: {list(METHODS)}")
    return METHODS[method]


def default_config(method: str) -> dict[str, Any]:
    """The paper's values for ``method`` as a plain dict (what ``recipes/<method>/config.yaml`` holds)."""
    m = _method(method)
    family = imitation_config.defaults(method) if m.family in IMITATION_FAMILIES else _FAMILY[m.family]
    cfg = {"method": method, **copy.deepcopy(_COMMON), **copy.deepcopy(family)}
    if m.lagrangian:
        cfg["constraint"] = copy.deepcopy(_LAGRANGIAN[m.family])
        if m.family == "sac":
            cfg["loss"].update(_SAC_LAG_LOSS)
    order = ["method", "seed", "profile", "env", "mentor", "data", "collector", "replay_buffer", "optim", "loss",
             "discriminator", "constraint", "logger", "eval", "checkpoint"]
    return {k: cfg[k] for k in order if k in cfg}


def profiles(method: str) -> dict[str, dict[str, Any]]:
    """``{profile name: overrides}`` for ``method`` (``paper``: none; ``cpu``: 30K env steps; ``smoke``: CI)."""
    family = _method(method).family
    return imitation_config.profiles(method) if family in IMITATION_FAMILIES else copy.deepcopy(_PROFILES[family])


def recipe_config_path(method: str) -> Path | None:
    """``recipes/<method>/config.yaml``: under ``$PE_RLHF_RECIPES`` if set, else the first ``recipes/``
    found walking up from this file; None if neither (an installed package uses :func:`default_config`)."""
    relative = Path(method) / "config.yaml"
    root = os.environ.get(RECIPES_ENV_VAR)
    if root:
        path = Path(root) / relative
        return path if path.is_file() else None
    for parent in Path(__file__).resolve().parents:
        path = parent / "recipes" / relative
        if path.is_file():
            return path
    return None


def load_baseline_config(method: str, path: str | Path | None = None, overrides=(), *,
                         apply_profile: bool = True, validate: bool = True) -> DictConfig:
    """Defaults <- YAML file <- profile <- dotlist overrides, validated (module docstring).

    ``apply_profile=False``: for a config written by :func:`~pe_rlhf.training.config.save_config` (a run's
    ``config.yaml``), whose values already include its profile and overrides.
    """
    _method(method)
    cfg = OmegaConf.create(default_config(method))
    OmegaConf.set_struct(cfg, True)
    OmegaConf.set_struct(cfg.env, False)
    if "mentor" in cfg:
        OmegaConf.set_struct(cfg.mentor.kwargs, False)
    path = Path(path) if path is not None else recipe_config_path(method)
    if path is not None:
        if not path.is_file():
            raise ConfigError(f"config file {str(path)!r} not found")
        values, recorded = read_config_file(path)
        merge_values(cfg, values, f"config file {path}")
        check_recorded_algorithm(recorded, algorithm_name(method))
    parsed = parse_overrides(overrides)
    profile = next((v.strip() for k, v in reversed(parsed) if k == "profile"), cfg.profile)
    if profile not in PROFILE_NAMES:
        raise invalid_value("profile", profile, f"allowed: {list(PROFILE_NAMES)}")
    if apply_profile:
        merge_values(cfg, profiles(method)[profile], f"profile {profile!r}")
    cfg.profile = profile
    for key, value in parsed:
        check_key(cfg, key, "command-line override")
        try:
            cfg.merge_with(OmegaConf.from_dotlist([f"{key}={value}"]))
        except OmegaConfBaseException as e:
            raise ConfigError(f"cannot apply override {key}={value}: {e}", key) from e
    if validate:
        validate_baseline_config(cfg, method)
    return cfg


# --------------------------------------------------------------------------- field rules

RULES = {
    "method": rule_choice(*METHODS), "seed": rule_int(0), "profile": rule_choice(*PROFILE_NAMES),
    "collector.total_frames": rule_int(1), "collector.frames_per_batch": rule_int(1),
    "collector.learning_starts": rule_int(0), "collector.init_random_frames": rule_int(0),
    "replay_buffer.size": rule_int(1), "replay_buffer.batch_size": rule_int(1),
    "optim.lr": rule_number(0, lo_open=True), "optim.updates_per_batch": rule_int(1), "optim.epochs": rule_int(1),
    "optim.minibatch_size": rule_int(1), "optim.max_grad_norm": rule_optional(rule_number(0, lo_open=True)),
    "optim.precision": rule_choice(*PRECISIONS),
    "loss.gamma": rule_number(0, 1), "loss.tau": rule_number(0, 1, lo_open=True), "loss.num_qvalue_nets": rule_int(1),
    "loss.target_entropy": rule_target_entropy, "loss.alpha_init": rule_number(0, lo_open=True), "loss.hidden": rule_hidden,
    "loss.deactivate_vmap": rule_bool,
    "loss.num_cost_qvalue_nets": rule_int(1), "loss.cost_aggregate": rule_choice("max", "mean", "min"),
    "loss.gae_lambda": rule_number(0, 1), "loss.clip_epsilon": rule_number(0, lo_open=True), "loss.kl_coef": rule_number(0),
    "loss.kl_target": rule_optional(rule_number(0, lo_open=True)), "loss.entropy_coef": rule_number(0),
    "loss.critic_coef": rule_number(0), "loss.normalize_advantage": rule_bool,
    "loss.target_kl": rule_number(0, lo_open=True), "loss.cg_iterations": rule_int(1), "loss.cg_damping": rule_number(0),
    "loss.backtrack_ratio": rule_number(0, 1, lo_open=True, hi_open=True), "loss.max_backtracks": rule_int(1),
    "constraint.cost_limit": rule_number(0), "constraint.window": rule_int(1),
    "constraint.lambda_lr": rule_number(0, lo_open=True), "constraint.lambda_init": rule_number(0),
    "logger.out_dir": rule_optional(rule_string), **{f"logger.{k}": rule_bool for k in ("csv", "wandb", "tensorboard", "mlflow")},
    "logger.wandb_mode": rule_choice(*WANDB_MODES), "logger.wandb_project": rule_string, "logger.log_every": rule_int(1),
    "eval.every_frames": rule_int(0), "eval.episodes": rule_int(1), "eval.split": rule_choice(*SPLITS),
    "checkpoint.every_frames": rule_int(0), "checkpoint.keep": rule_int(1),
    **imitation_config.RULES,
}


def validate_baseline_config(cfg: DictConfig, method: str) -> None:
    """Check every field of ``method``'s config (:data:`RULES`), the env (as a DrivingConfig) and the
    fields that bound each other; raise :class:`ConfigError` naming the first bad field."""
    expected = set(leaf_keys(default_config(method)))
    present = set(leaf_keys(OmegaConf.to_container(cfg)))
    for key in sorted(present - expected - {"env", "mentor.kwargs"}):
        raise ConfigError(f"unknown config key {key!r} for {method}; known: {sorted(expected)}", key)
    for key in sorted(expected - {"env"}):
        value = OmegaConf.select(cfg, key, default=_MISSING)
        if value is _MISSING:
            raise ConfigError(f"{key} is missing from the config", key)
        problem = RULES[key](value)
        if problem is not None:
            raise invalid_value(key, value, problem)
    if cfg.method != method:
        raise invalid_value("method", cfg.method, f"this is the {method} recipe's config (method: {method})")
    check_env(cfg.env)
    _check_relations(cfg, METHODS[method])


_MISSING = object()


def _check_relations(cfg: DictConfig, m: Method) -> None:
    from pe_rlhf.envs import scene_seeds

    scenes = len(scene_seeds(str(cfg.eval.split)))
    if cfg.eval.episodes > scenes:
        raise invalid_value("eval.episodes", cfg.eval.episodes, f"must be <= {scenes}: one episode per scene of the "
                    f"{cfg.eval.split} split")
    if m.family in IMITATION_FAMILIES:
        imitation_config.check_relations(cfg, m.family)
    if m.family == "offline":
        return
    c = cfg.collector
    if c.frames_per_batch > c.total_frames:
        raise invalid_value("collector.frames_per_batch", c.frames_per_batch,
                    f"must be <= collector.total_frames ({c.total_frames})")
    if m.family == "sac":
        if c.learning_starts >= c.total_frames:
            raise invalid_value("collector.learning_starts", c.learning_starts,
                        f"must be < collector.total_frames ({c.total_frames}), or no update ever runs")
        if cfg.replay_buffer.batch_size > cfg.replay_buffer.size:
            raise invalid_value("replay_buffer.batch_size", cfg.replay_buffer.batch_size,
                        f"must be <= replay_buffer.size ({cfg.replay_buffer.size})")
    elif m.family in ("ppo", "cpo", "gail") and cfg.optim.minibatch_size > c.frames_per_batch:
        raise invalid_value("optim.minibatch_size", cfg.optim.minibatch_size,
                    f"must be <= collector.frames_per_batch ({c.frames_per_batch}): minibatches split each batch")


def algorithm_name(method: str) -> str:
    """The registry name (:data:`pe_rlhf.algorithms.ALGORITHMS`) of the baseline ``method`` (``sac_rs`` ->
    ``sac-rs``), as its run folder records it."""
    return method.replace("_", "-")


def method_of(cfg: DictConfig) -> Method:
    """The :class:`Method` a validated config describes."""
    return METHODS[str(cfg.method)]


__all__ = ["METHODS", "PROFILE_NAMES", "RULES", "Method", "algorithm_name", "default_config", "load_baseline_config",
           "method_of", "profiles", "recipe_config_path", "validate_baseline_config"]
