"""The recipe's configuration: load ``config.yaml``, apply a profile and overrides, validate every field.

``load_config(path, overrides)`` layers, each on top of the one before:

1. :data:`DEFAULTS` (the paper's values; a copy of ``recipes/pe_rlhf/config.yaml``, kept equal by a test),
2. the YAML file (``path``, or the recipe's own ``config.yaml`` when found; may be partial),
3. the profile's overrides (:data:`PROFILES`; ``profile`` from the overrides, else from the file),
4. the dotlist overrides (``["optim.lr=3e-4", "mentor.name=amateur"]``),

then :func:`validate_config`. Every group is closed (struct mode): an unknown key fails naming it.
Two groups are open by design and checked by name instead: ``env`` (any
:class:`~pe_rlhf.envs.config.DrivingConfig` field) and ``mentor.kwargs`` (arguments to ``make_mentor``).
Every error is a :class:`ConfigError` (a ``ValueError``) that names the dotted field, the value and
what is allowed.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import math
import os
import re
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.modules.precision import PRECISIONS
from pe_rlhf.objectives.perlhf import FAILURE_TARGETS, GAP_ACTIONS
from pe_rlhf.physics.safety import RECOVERIES

RECIPES_ENV_VAR = "PE_RLHF_RECIPES"
RECIPE_CONFIG = Path("pe_rlhf") / "config.yaml"  # relative to the recipes directory
OPEN_GROUPS = ("env", "mentor.kwargs")  # free-form groups, checked by name in validate_config
# A run's saved config.yaml records the run's method by its registry name (pe_rlhf.algorithms.ALGORITHMS) under
# this top-level key; the loaders read it apart from the config values and check it against them.
ALGORITHM_KEY = "algorithm"
PROXY_Q_ALGORITHMS = ("pe-rlhf", "haco", "haim-drl")  # this recipe's methods, by registry name

# The paper's values (spec §3). Keep equal to recipes/pe_rlhf/config.yaml (tests/training/test_training_config.py).
DEFAULTS: dict[str, Any] = {
    "seed": 0,
    "profile": "paper",
    "env": {"lane_features": True},
    "mentor": {"name": "professional", "seed": 0, "kwargs": {}},
    "physics": {"enabled": True, "see_obstacles": False, "stop_for_obstacles": True, "use_idm": True, "use_mobil": True},
    "selector": {"enabled": True, "value": "forecast", "epsilon_select": None, "variance_threshold": None,
                 "switch_margin": None, "veto_patience": 1, "imminent_failure": None, "forecast_hold": 1.0,
                 "forecast_hold_one_lane": False, "forecast_recovery": "route", "warmup_selection": False, "num_members": 5,
                 "hidden": [256, 256], "warmup_fit_steps": 3000, "refresh_every": 0, "refresh_steps": 500,
                 "refresh_data": "warmup",
                 "fit_loss": "mean", "target_noise": 0.1, "tau": 0.005, "lr": 3.0e-4, "batch_size": 256},
    "collector": {"total_frames": 30000, "frames_per_batch": 100, "warmup_steps": 10000,
                  "warmup_policy": None, "warmup_gap": True, "learning_starts": 100, "exploration": "random", "backend": "single", "num_workers": 1,
                  "realtime_hz": 0},
    "replay_buffer": {"size": 100000, "batch_size": 1024},
    "optim": {"lr": 1.0e-4, "updates_per_batch": 100, "max_grad_norm": 10.0, "async_updates": False,
              "threads": "auto", "device": "auto", "precision": "fp32"},
    "loss": {"gamma": 0.99, "tau": 0.005, "gap_coef": 10.0, "gap_margin": None, "psi": 1.0, "intervention_weight": 1.0,
             "cosine_cost": True, "intervention_critic_action": "agent", "num_qvalue_nets": 2,
             "num_intervention_qvalue_nets": 1, "target_entropy": "auto", "alpha_init": 1.0,
             "hidden": [256, 256], "disturbance_weight": 1.0, "num_disturbance_qvalue_nets": 2,
             "failure_target": "batch_min", "gap_action": "agent", "fused_critics": True},
    "disturbance": {"enabled": False, "threshold": 5.0, "horizon": 3.0, "follower_range": 60.0},
    "logger": {"out_dir": None, "csv": True, "wandb": False, "wandb_mode": "offline",
               "wandb_project": "pe-rlhf", "tensorboard": False, "mlflow": False, "log_every": 1},
    "eval": {"every_frames": 5000, "episodes": 10, "split": "test", "video": True},
    "checkpoint": {"every_frames": 5000, "keep": 2},
}

PROFILES: dict[str, dict[str, Any]] = {
    # The paper's appendix values: DEFAULTS / config.yaml unchanged.
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
    "quick": {
        "selector": {"warmup_fit_steps": 1500},
        "collector": {"total_frames": 9000, "warmup_steps": 5000},
        "replay_buffer": {"batch_size": 256},
        "eval": {"every_frames": 0, "episodes": 10, "video": True},
        "checkpoint": {"every_frames": 3000},
    },
    # CI: the whole loop (warm-up, ensemble fit, updates, eval, checkpoint) in about a minute.
    "smoke": {
        "env": {"horizon": 100, "min_blocks": 2, "max_blocks": 2},
        "selector": {"num_members": 2, "hidden": [32, 32], "warmup_fit_steps": 20, "refresh_steps": 10,
                     "batch_size": 32},
        "collector": {"total_frames": 300, "frames_per_batch": 50, "warmup_steps": 100, "learning_starts": 50},
        "replay_buffer": {"size": 1000, "batch_size": 32},
        "optim": {"updates_per_batch": 5},
        "loss": {"hidden": [32, 32]},
        "eval": {"every_frames": 300, "episodes": 1, "video": True},
        "checkpoint": {"every_frames": 300, "keep": 1},
    },
}

# A person drives at a steady frame rate while the learner runs beside acting (see
# pe_rlhf.transforms.RealtimePacing, pe_rlhf.training.background_updates); load_config applies these
# with mentor.name=human unless the fields are given, so the saved config shows the values used.
HUMAN_DEFAULTS: dict[str, Any] = {"collector.realtime_hz": 10.0, "optim.async_updates": True}

BACKENDS = ("single", "multisync", "multiasync", "ray")
FIT_LOSSES = ("mean", "member")
REFRESH_DATA = ("warmup", "all")
INTERVENTION_CRITIC_ACTIONS = ("agent", "behavior")
WANDB_MODES = ("offline", "online", "disabled")
SPLITS = ("train", "test")
_IMPORT_PATH = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*$")


class ConfigError(ValueError):
    """An invalid configuration value; ``field`` is the dotted name (``optim.lr``) when known."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


def invalid_value(field: str, value: Any, allowed: str) -> ConfigError:
    if isinstance(value, (DictConfig, ListConfig)):
        value = OmegaConf.to_container(value)
    return ConfigError(f"{field}={value!r} is invalid: {allowed}", field)


# --------------------------------------------------------------------------- loading


def default_config_path() -> Path | None:
    """The recipe's ``config.yaml``: under ``$PE_RLHF_RECIPES`` if set, else the first ``recipes/``
    found walking up from this file (a source checkout); None if neither (an installed package,
    which then uses :data:`DEFAULTS`)."""
    root = os.environ.get(RECIPES_ENV_VAR)
    if root:
        path = Path(root) / RECIPE_CONFIG
        if not path.is_file():
            raise ConfigError(f"${RECIPES_ENV_VAR}={root!r} has no {RECIPE_CONFIG}")
        return path
    for parent in Path(__file__).resolve().parents:
        path = parent / "recipes" / RECIPE_CONFIG
        if path.is_file():
            return path
    return None


def check_key(cfg: DictConfig, key: str, origin: str) -> None:
    """Fail unless ``key`` (dotted) exists in ``cfg`` or lies inside an open group."""
    node: Any = cfg
    parts = key.split(".")
    for i, part in enumerate(parts):
        prefix = ".".join(parts[:i]) or "the config"
        if not isinstance(node, DictConfig):
            raise ConfigError(f"unknown config key {key!r} ({origin}): {prefix} is a value, not a group", key)
        if not OmegaConf.is_struct(node):
            return
        if part not in node:
            raise ConfigError(f"unknown config key {key!r} ({origin}): {prefix} has no {part!r}; "
                              f"known: {sorted(node.keys())}", key)
        node = node[part]


def leaf_keys(values: Mapping, prefix: str = "") -> Iterable[str]:
    for key, value in values.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping) and value and path not in OPEN_GROUPS:
            yield from leaf_keys(value, path + ".")
        else:
            yield path


def merge_values(cfg: DictConfig, values: Mapping | DictConfig, origin: str) -> None:
    if isinstance(values, DictConfig):
        values = OmegaConf.to_container(values)
    if not isinstance(values, Mapping):
        raise ConfigError(f"{origin} must be a mapping of config groups, got {type(values).__name__}")
    for key in leaf_keys(values):
        check_key(cfg, key, origin)
    try:
        cfg.merge_with(values)
    except OmegaConfBaseException as e:
        raise ConfigError(f"cannot apply {origin}: {e}") from e


def parse_overrides(overrides: Iterable[str]) -> list[tuple[str, str]]:
    if isinstance(overrides, str):  # a lone "a=b" would otherwise be iterated character by character
        overrides = [overrides]
    parsed = []
    for item in overrides:
        if not isinstance(item, str) or "=" not in item or not item.split("=", 1)[0].strip():
            raise ConfigError(f"override {item!r} is not of the form key=value (e.g. optim.lr=3e-4)")
        key, value = item.split("=", 1)
        parsed.append((key.strip(), value))
    return parsed


def load_config(path: str | Path | None = None, overrides: Iterable[str] = (), *,
                apply_profile: bool = True, validate: bool = True) -> DictConfig:
    """DEFAULTS <- YAML file <- profile <- dotlist overrides, validated (see the module docstring).

    ``path=None`` reads the recipe's ``config.yaml`` (:func:`default_config_path`), or uses
    :data:`DEFAULTS` alone when there is none. ``overrides`` are ``key=value`` strings, values in
    YAML syntax (``loss.hidden=[128,128]``, ``selector.variance_threshold=null``).
    ``apply_profile=False`` skips step 3 (the profile is only recorded): for a config written by
    :func:`save_config`, whose values already include its profile and overrides.
    """
    cfg = OmegaConf.create(copy.deepcopy(DEFAULTS))
    OmegaConf.set_struct(cfg, True)
    for group in OPEN_GROUPS:
        OmegaConf.set_struct(OmegaConf.select(cfg, group), False)
    path = Path(path) if path is not None else default_config_path()
    recorded = None  # the method a run's saved config records (read_config_file)
    if path is not None:
        if not Path(path).is_file():
            raise ConfigError(f"config file {str(path)!r} not found")
        values, recorded = read_config_file(path)
        merge_values(cfg, values, f"config file {path}")
    parsed = parse_overrides(overrides)
    profile = next((v.strip() for k, v in reversed(parsed) if k == "profile"), cfg.profile)
    if profile not in PROFILES:
        raise invalid_value("profile", profile, f"allowed: {list(PROFILES)}")
    if apply_profile:
        merge_values(cfg, PROFILES[profile], f"profile {profile!r}")
    cfg.profile = profile
    given = {key for key, value in HUMAN_DEFAULTS.items() if OmegaConf.select(cfg, key) != _default(key)}
    for key, value in parsed:
        check_key(cfg, key, "command-line override")
        try:
            cfg.merge_with(OmegaConf.from_dotlist([f"{key}={value}"]))
        except OmegaConfBaseException as e:
            raise ConfigError(f"cannot apply override {key}={value}: {e}", key) from e
        given.add(key)
    if apply_profile:  # a saved config (apply_profile=False) holds its resolved values already
        _apply_human_defaults(cfg, given)
    if validate:
        validate_config(cfg)
        check_recorded_algorithm(recorded, algorithm_name(cfg))
    return cfg


def read_config_file(path: str | Path) -> tuple[dict[str, Any], str | None]:
    """A config file's values, and apart from them the registry name a run recorded under :data:`ALGORITHM_KEY`
    (None: a recipe's config, or a run folder written before runs recorded it)."""
    values = OmegaConf.to_container(OmegaConf.load(path))
    recorded = values.pop(ALGORITHM_KEY, None) if isinstance(values, dict) else None
    return values, None if recorded is None else str(recorded)


def check_recorded_algorithm(recorded: str | None, expected: str) -> None:
    """Refuse a saved config whose recorded method is not the one its values describe (e.g. a HACO run folder
    resumed with ``physics.enabled=true``)."""
    if recorded is not None and recorded != expected:
        raise invalid_value(ALGORITHM_KEY, recorded, f"the run folder's config describes {expected!r}; resume a "
                            "run with the values it was started with")


def _default(key: str) -> Any:
    node: Any = DEFAULTS
    for part in key.split("."):
        node = node[part]
    return node


def _apply_human_defaults(cfg: DictConfig, given: set[str]) -> None:
    """With ``mentor.name=human``, :data:`HUMAN_DEFAULTS` for the fields not given (a field counts as
    given when an override names it, or the file or profile sets it to a non-default value)."""
    if cfg.mentor.name != "human":
        return
    for key, value in HUMAN_DEFAULTS.items():
        if key not in given:
            OmegaConf.update(cfg, key, value)


# --------------------------------------------------------------------------- field rules

Rule = Callable[[Any], str | None]  # value -> None if fine, else what is allowed


def rule_int(minimum: int) -> Rule:
    def rule(v):
        ok = isinstance(v, int) and not isinstance(v, bool) and v >= minimum
        return None if ok else f"must be an integer >= {minimum}"
    return rule


def rule_number(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
            hi_open: bool = False, meaning: str = "") -> Rule:
    """A finite number in the bounds; ``meaning`` (what the values do) is appended to the message."""
    if lo is not None and hi is not None:
        allowed = f"must be a finite number in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    elif lo is not None:
        allowed = f"must be a finite number {'>' if lo_open else '>='} {lo}"
    else:
        allowed = "must be a finite number"
    allowed += f" ({meaning})" if meaning else ""

    def rule(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return allowed
        if lo is not None and (v < lo or (lo_open and v == lo)):
            return allowed
        if hi is not None and (v > hi or (hi_open and v == hi)):
            return allowed
        return None
    return rule


def rule_optional(rule: Rule) -> Rule:
    return lambda v: None if v is None else (None if rule(v) is None else f"{rule(v)}, or null")


def rule_bool(v) -> str | None:
    return None if isinstance(v, bool) else "must be true or false"


def rule_choice(*options: str) -> Rule:
    return lambda v: None if v in options else f"allowed: {list(options)}"


def rule_string(v) -> str | None:
    return None if isinstance(v, str) and v.strip() else "must be a non-empty string"


def rule_hidden(v) -> str | None:
    ok = isinstance(v, (list, tuple, ListConfig)) and len(v) > 0 and all(
        isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in v)
    return None if ok else "must be a non-empty list of positive integers (layer widths), e.g. [256, 256]"


def rule_target_entropy(v) -> str | None:
    return None if v == "auto" or rule_number()(v) is None else "must be 'auto' (= -dim(action)) or a finite number"


def rule_mentor_name(v) -> str | None:
    from pe_rlhf.mentors.registry import MENTOR_NAMES

    if isinstance(v, str) and (v in MENTOR_NAMES or _IMPORT_PATH.match(v)):
        return None
    return f"allowed: {list(MENTOR_NAMES)} or a 'package.module:ClassName' import path"


def _value_source(v) -> str | None:
    from pe_rlhf.training.value_expert import packaged_expert_path, parse_value_source

    try:
        _, path = parse_value_source(v)
    except ValueError as err:
        return str(err).split("; ", 1)[1]
    path = path if path is not None or v != "expert" else packaged_expert_path()
    if path is not None and not path.exists():
        return f"{str(path)!r} does not exist (a Q-ensemble file or a run folder)"
    return None


def _backend(v) -> str | None:
    if v not in BACKENDS:
        return f"allowed: {list(BACKENDS)}"
    if v == "ray" and importlib.util.find_spec("ray") is None:
        return "'ray' needs the ray package, which is not installed (pip install ray); use multisync or multiasync"
    return None


# HybridActionSelector keeps the mentor iff mean_k[Q_k(s, a_mentor) - Q_k(s, a_phy)] >= epsilon_select.
EPSILON_SELECT_MEANING = ("any sign, in the value source's units: > 0 the mentor must be valued that much above "
                          "physics, 0 the higher-valued action wins, < 0 physics vetoes the mentor only when valued "
                          "-epsilon_select above it")

RULES: dict[str, Rule] = {
    "seed": rule_int(0),
    "profile": rule_choice(*PROFILES),
    "mentor.name": rule_mentor_name, "mentor.seed": rule_int(0),
    **{f"physics.{k}": rule_bool for k in ("enabled", "see_obstacles", "stop_for_obstacles", "use_idm", "use_mobil")},
    "selector.enabled": rule_bool, "selector.epsilon_select": rule_optional(rule_number(meaning=EPSILON_SELECT_MEANING)),
    "selector.variance_threshold": rule_optional(rule_number(0)), "selector.num_members": rule_int(1),
    "selector.hidden": rule_hidden, "selector.warmup_fit_steps": rule_int(0), "selector.refresh_every": rule_int(0),
    "selector.refresh_steps": rule_int(0), "selector.fit_loss": rule_choice(*FIT_LOSSES),
    "selector.refresh_data": rule_choice(*REFRESH_DATA),
    "selector.value": _value_source, "selector.switch_margin": rule_optional(rule_number(0)),
    "selector.forecast_hold": rule_number(0, 3), "selector.forecast_hold_one_lane": rule_bool,
    "selector.forecast_recovery": rule_choice(*RECOVERIES), "selector.veto_patience": rule_int(1),
    "selector.imminent_failure": rule_optional(rule_number()),
    "selector.warmup_selection": lambda v: None if v == "auto" or isinstance(v, bool) else "allowed: auto, true, false",
    "selector.target_noise": rule_number(0), "selector.tau": rule_number(0, 1, lo_open=True), "selector.lr": rule_number(0, lo_open=True),
    "selector.batch_size": rule_int(1),
    "collector.total_frames": rule_int(1), "collector.frames_per_batch": rule_int(1),
    "collector.warmup_steps": rule_int(0), "collector.warmup_policy": rule_optional(rule_string), "collector.warmup_gap": rule_bool, "collector.exploration": rule_choice("random", "deterministic"), "collector.learning_starts": rule_int(0),
    "collector.backend": _backend, "collector.num_workers": rule_int(1), "collector.realtime_hz": rule_number(0),
    "replay_buffer.size": rule_int(1), "replay_buffer.batch_size": rule_int(1),
    "optim.lr": rule_number(0, lo_open=True), "optim.updates_per_batch": rule_int(1),
    "optim.max_grad_norm": rule_optional(rule_number(0, lo_open=True)), "optim.async_updates": rule_bool,
    "optim.device": lambda v: None if isinstance(v, str) and re.fullmatch(r"auto|cpu|cuda(:\d+)?", v)
    else "allowed: auto, cpu, cuda, cuda:N",
    "optim.threads": lambda v: None if v == "auto" or (isinstance(v, int) and not isinstance(v, bool) and v >= 1)
    else "allowed: auto, or an int >= 1",
    "optim.precision": rule_choice(*PRECISIONS),
    "loss.gamma": rule_number(0, 1), "loss.tau": rule_number(0, 1, lo_open=True), "loss.gap_coef": rule_number(0), "loss.gap_margin": rule_optional(rule_number(0)),
    "loss.psi": rule_number(0), "loss.intervention_weight": rule_number(0), "loss.cosine_cost": rule_bool,
    "loss.intervention_critic_action": rule_choice(*INTERVENTION_CRITIC_ACTIONS),
    "loss.num_qvalue_nets": rule_int(1), "loss.num_intervention_qvalue_nets": rule_int(1),
    "loss.target_entropy": rule_target_entropy, "loss.alpha_init": rule_number(0, lo_open=True), "loss.hidden": rule_hidden,
    "loss.disturbance_weight": rule_number(0), "loss.num_disturbance_qvalue_nets": rule_int(1),
    "loss.failure_target": rule_choice(*FAILURE_TARGETS), "loss.gap_action": rule_choice(*GAP_ACTIONS),
    "loss.fused_critics": rule_bool,
    "disturbance.enabled": rule_bool, **{f"disturbance.{k}": rule_number(0, lo_open=True)
                                      for k in ("threshold", "horizon", "follower_range")},
    "logger.out_dir": rule_optional(rule_string), **{f"logger.{k}": rule_bool for k in ("csv", "wandb", "tensorboard", "mlflow")},
    "logger.wandb_mode": rule_choice(*WANDB_MODES), "logger.wandb_project": rule_string, "logger.log_every": rule_int(1),
    "eval.every_frames": rule_int(0), "eval.episodes": rule_int(1), "eval.split": rule_choice(*SPLITS), "eval.video": rule_bool,
    "checkpoint.every_frames": rule_int(0), "checkpoint.keep": rule_int(1),
}


# --------------------------------------------------------------------------- validation


_PROBE = "\0"  # a value every rule refuses (its message says what is allowed); a plain string rule accepts it


def reference_table() -> str:
    """The recipe config's fields as a Markdown table: field, default, what is allowed (each rule's own words).

    ``docs/guide/configuration.md`` holds this table (a test keeps them equal). ``env.*`` takes any
    ``DrivingConfig`` field and ``mentor.kwargs`` the mentor's arguments; their checks are listed below it.
    """
    rows = ["| field | default | allowed |", "|---|---|---|"]
    for field, rule in RULES.items():
        default = _default(field)
        allowed = rule(_PROBE) or ("a non-empty string" + (", or null" if default is None else ""))
        shown = "null" if default is None else str(default).lower() if isinstance(default, bool) else default
        rows.append(f"| `{field}` | `{shown}` | {allowed.replace('|', '/')} |")
    return "\n".join(rows)


def validate_config(cfg: DictConfig) -> None:
    """Check every field (:data:`RULES`), the env (as a DrivingConfig), the mentor's kwargs, and the
    fields that constrain each other; raise :class:`ConfigError` at the first problem."""
    for key in leaf_keys(OmegaConf.to_container(cfg)):
        if key not in RULES and key not in OPEN_GROUPS:
            raise ConfigError(f"unknown config key {key!r}; known: {sorted(RULES) + list(OPEN_GROUPS)}", key)
    for field, rule in RULES.items():
        value = OmegaConf.select(cfg, field, default=_MISSING)
        if value is _MISSING:
            raise ConfigError(f"{field} is missing from the config", field)
        problem = rule(value)
        if problem is not None:
            raise invalid_value(field, value, problem)
    check_env(cfg.env)
    check_mentor_kwargs(cfg.mentor)
    _check_relations(cfg)


_MISSING = object()


def _check_relations(cfg: DictConfig) -> None:
    c = cfg.collector
    pairs = (("collector.frames_per_batch", c.frames_per_batch, "collector.total_frames", c.total_frames),
             ("collector.warmup_steps", c.warmup_steps, "collector.total_frames", c.total_frames),
             ("replay_buffer.batch_size", cfg.replay_buffer.batch_size, "replay_buffer.size", cfg.replay_buffer.size))
    for field, value, bound_field, bound in pairs:
        if value > bound:
            raise invalid_value(field, value, f"must be <= {bound_field} ({bound})")
    if c.learning_starts >= c.total_frames:
        raise invalid_value("collector.learning_starts", c.learning_starts,
                    f"must be < collector.total_frames ({c.total_frames}), or no update ever runs")
    if c.backend == "single" and c.num_workers != 1:
        raise invalid_value("collector.num_workers", c.num_workers,
                    "the single backend runs one env: use 1, or collector.backend=multisync|multiasync")
    if cfg.mentor.name == "human" and c.backend != "single":
        raise invalid_value("collector.backend", c.backend, "a human mentor drives one env in this process (one person, "
                    "one window): use single")
    if c.backend in ("multisync", "ray") and c.frames_per_batch % c.num_workers:
        raise invalid_value("collector.frames_per_batch", c.frames_per_batch,
                    f"must be divisible by collector.num_workers ({c.num_workers}): with collector.backend="
                    f"{c.backend} each worker collects an equal share of every batch")
    if c.backend != "single":
        for field, value in (("collector.realtime_hz", c.realtime_hz),
                             ("optim.async_updates", cfg.optim.async_updates)):
            if value:
                raise invalid_value(field, value, f"needs collector.backend=single (got {c.backend}): the pacing and the "
                            "background learner drive one env in this process; use 0 / false")
    if c.warmup_policy is not None and c.warmup_steps < 1:
        raise invalid_value("collector.warmup_policy", c.warmup_policy,
                    "drives the warm-up, but collector.warmup_steps is 0: give the warm-up steps, or null")
    method_name(cfg)  # physics/selector combination
    if cfg.selector.enabled and cfg.selector.warmup_selection is True:
        from pe_rlhf.training.value_expert import parse_value_source

        if parse_value_source(cfg.selector.value)[0] == "warmup":
            raise invalid_value("selector.warmup_selection", True, "needs a value source that is not fitted on the warm-up "
                        "(selector.value=forecast or expert): use auto or false")
        if c.warmup_policy is not None:
            raise invalid_value("selector.warmup_selection", True, "judges the mentor's warm-up, but collector.warmup_policy "
                        "drives it: use auto or false")
    if cfg.selector.enabled:
        for field in ("collector.warmup_steps", "selector.warmup_fit_steps"):
            if OmegaConf.select(cfg, field) < 1:
                raise invalid_value(field, OmegaConf.select(cfg, field),
                            "must be >= 1 with selector.enabled (the Q-ensemble is fitted on warm-up data)")


def _env_type_problem(default: Any, value: Any) -> str | None:
    """What DrivingConfig would choke on with a TypeError (or accept wrongly): judged by the default's type."""
    if isinstance(default, bool):
        return rule_bool(value)
    if isinstance(default, int):
        return None if isinstance(value, int) and not isinstance(value, bool) else "must be an integer"
    if isinstance(default, float):
        return None if rule_number()(value) is None else "must be a finite number"
    if isinstance(default, tuple):
        ok = isinstance(value, (list, tuple)) and all(isinstance(x, str) for x in value)
        return None if ok else "must be a list of names"
    return None


def check_env(env: DictConfig) -> None:
    values = OmegaConf.to_container(env, resolve=True)
    defaults = DrivingConfig()
    known = [f.name for f in dataclasses.fields(DrivingConfig)]
    for key, value in values.items():
        if key not in known:
            raise invalid_value(f"env.{key}", value, f"unknown DrivingConfig field; known: {known}")
        problem = _env_type_problem(getattr(defaults, key), value)
        if problem:
            raise invalid_value(f"env.{key}", value, problem)
    try:
        DrivingConfig.from_dict(values)
    except (ValueError, TypeError) as e:
        match = re.match(r"DrivingConfig\.(\w+)=(.*?) is invalid: (.*)", str(e), re.S)
        if match is None:
            raise ConfigError(f"env={values!r} is invalid: {e}", "env") from e
        name, shown, allowed = match.groups()
        raise ConfigError(f"env.{name}={shown} is invalid: {allowed}", f"env.{name}") from e


def check_mentor_kwargs(mentor: DictConfig) -> None:
    if ":" in mentor.name:
        return  # a user's class: its constructor arguments are checked when it is built
    if mentor.name == "human":
        _check_human_kwargs(mentor.kwargs)
        return
    if mentor.name == "collapsing":
        from pe_rlhf.mentors.collapsing import COLLAPSING_KWARGS

        for key in mentor.kwargs:
            if key not in COLLAPSING_KWARGS:
                raise invalid_value(f"mentor.kwargs.{key}", mentor.kwargs[key],
                            f"unknown CollapsingMentor argument; known: {list(COLLAPSING_KWARGS)}")
        return
    from pe_rlhf.mentors.simulated import SkillProfile

    known = sorted(f.name for f in dataclasses.fields(SkillProfile))
    for key in mentor.kwargs:
        if key not in known:
            raise invalid_value(f"mentor.kwargs.{key}", mentor.kwargs[key],
                        f"unknown SkillProfile field for mentor {mentor.name!r}; known: {known}")


def _window_size(v) -> str | None:
    ok = isinstance(v, (list, tuple, ListConfig)) and len(v) == 2 and all(rule_int(1)(x) is None for x in v)
    return None if ok else "must be [width, height] in pixels"


# HumanMentor arguments a YAML value can give (mapping / input_state are objects, for code only).
HUMAN_KWARGS: dict[str, Rule] = {"fps": rule_number(0), "scaling": rule_number(0, lo_open=True), "title": rule_string,
                                 "size": _window_size, "on_disconnect": rule_choice("agent", "pause")}


def _check_human_kwargs(kwargs: DictConfig) -> None:
    for key in kwargs:
        if key not in HUMAN_KWARGS:
            raise invalid_value(f"mentor.kwargs.{key}", kwargs[key],
                        f"unknown HumanMentor argument; known: {sorted(HUMAN_KWARGS)}")
        problem = HUMAN_KWARGS[key](kwargs[key])
        if problem is not None:
            raise invalid_value(f"mentor.kwargs.{key}", kwargs[key], problem)


# --------------------------------------------------------------------------- views


def method_name(cfg: DictConfig) -> str:
    """``"PE-RLHF"`` (physics + selector), ``"HACO"`` (neither) or ``"HAIM-DRL"`` (HACO with
    ``disturbance.enabled``; PE-RLHF with it is ``"PE-RLHF+disturbance"``); the mixed cases are errors.

    The intervention transform takes physics and selector together or not at all; the paper's
    "w/o ensemble" ablation is ``selector.num_members=1``, its physics ablations are
    ``physics.use_idm`` / ``physics.use_mobil``.
    """
    physics, selector = cfg.physics.enabled, cfg.selector.enabled
    disturbance = bool(cfg.disturbance.enabled)
    if physics and selector:
        return "PE-RLHF+disturbance" if disturbance else "PE-RLHF"
    if not physics and not selector:
        return "HAIM-DRL" if disturbance else "HACO"
    if selector:
        raise invalid_value("selector.enabled", True, "needs physics.enabled=true (PE-RLHF chooses between the "
                    "mentor's and the physics action); set both false for HACO")
    raise invalid_value("physics.enabled", True, "needs selector.enabled=true (the selector decides when the physics "
                "action replaces the mentor's); set both false for HACO, or selector.num_members=1 for the "
                "'w/o ensemble' ablation")


def algorithm_name(cfg: DictConfig) -> str:
    """The registry name (:data:`pe_rlhf.algorithms.ALGORITHMS`) of the method ``cfg`` describes, as a run records
    it: ``pe-rlhf``, ``haco`` or ``haim-drl`` (PE-RLHF with the disturbance critic is a ``pe-rlhf`` run)."""
    return method_name(cfg).removesuffix("+disturbance").lower()


def driving_config(cfg: DictConfig, **changes: Any) -> DrivingConfig:
    """The :class:`DrivingConfig` of ``cfg.env``, with ``changes`` on top (e.g. ``split="test"`` for eval)."""
    values = {**OmegaConf.to_container(cfg.env, resolve=True), **changes}
    check_env(OmegaConf.create(values))
    return DrivingConfig.from_dict(values)


def physics_config(cfg: DictConfig):
    """The :class:`~pe_rlhf.physics.policy.PhysicsConfig` of ``cfg.physics`` (paper IDM/MOBIL parameters)."""
    from pe_rlhf.physics.policy import PhysicsConfig

    p = cfg.physics
    return PhysicsConfig(see_obstacles=p.see_obstacles, stop_for_obstacles=p.stop_for_obstacles,
                         use_idm=p.use_idm, use_mobil=p.use_mobil)


def to_container(cfg: DictConfig) -> dict[str, Any]:
    """A plain, resolved ``dict`` copy of ``cfg`` (for checkpoints, loggers, ``json``)."""
    return OmegaConf.to_container(cfg, resolve=True)


def save_config(cfg: DictConfig, path: str | Path, algorithm: str | None = None) -> Path:
    """Write ``cfg`` (resolved) as YAML, with ``algorithm`` (a run's registry name) first as the top-level
    :data:`ALGORITHM_KEY`; ``load_config(path, apply_profile=False)`` reads it back equal (with the profile
    applied again, the profile's values would overwrite the saved overrides)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if algorithm is not None:
        cfg = OmegaConf.create({ALGORITHM_KEY: algorithm, **to_container(cfg)})
    OmegaConf.save(cfg, path, resolve=True)
    return path


__all__ = ["ALGORITHM_KEY", "BACKENDS", "DEFAULTS", "HUMAN_DEFAULTS", "PROFILES", "PROXY_Q_ALGORITHMS", "RULES",
           "ConfigError", "algorithm_name", "check_recorded_algorithm", "default_config_path", "driving_config",
           "load_config", "method_name", "physics_config", "read_config_file", "save_config", "to_container",
           "validate_config"]
