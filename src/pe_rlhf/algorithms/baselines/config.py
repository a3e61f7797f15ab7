"""The baselines' configuration: compose a recipe's ``config.yaml`` with Hydra, validate every field.

``load_baseline_config(method, path, overrides)`` composes, each layer on top of the one before, as
:func:`pe_rlhf.algorithms.proxy_q.config.load_config` does for PE-RLHF (the same composition, override grammar and
errors: :mod:`pe_rlhf.runtime.config_compose`):

1. the method's structured config (:data:`SCHEMAS`: :mod:`~pe_rlhf.algorithms.baselines.config_schema` and
   :mod:`~pe_rlhf.algorithms.baselines.imitation_schema`; ``<method>_schema`` in Hydra's ConfigStore: the one place for
   each field's default, type and rule),
2. the recipe file (``path``, or ``recipes/<method>/config.yaml`` when found; may be partial),
3. the profile, a config group (:data:`~pe_rlhf.algorithms.baselines.config_profiles.PROFILES`; ``profile=cpu`` on the
   command line, else the file's ``defaults`` list, or the ``profile:`` of a file without one),
4. the overrides, Hydra's ``key=value`` (``["optim.lr=3e-4", "constraint.cost_limit=0"]``),

then :func:`validate_baseline_config`. Every group is closed (an unknown key fails naming it) except ``env`` (any
:class:`~pe_rlhf.envs.config.DrivingConfig` field) and ``mentor.kwargs``. Errors are
:class:`~pe_rlhf.runtime.config_rules.ConfigError` naming the dotted field, the value and what is allowed.

Methods and families: :data:`METHODS` (:mod:`pe_rlhf.algorithms.baselines.config_schema`, which also says why the cost
limit 1 never binds here).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pe_rlhf.algorithms.baselines.config_profiles import PROFILE_NAMES, PROFILES
from pe_rlhf.algorithms.baselines.config_schema import (
    IMITATION_FAMILIES,
    METHODS,
    CpoConfig,
    Method,
    PpoLagConfig,
    PpoRsConfig,
    SacLagConfig,
    SacRsConfig,
)
from pe_rlhf.algorithms.baselines.imitation_schema import BCConfig, CQLConfig, GailConfig, HGDaggerConfig, IWRConfig
from pe_rlhf.runtime.config import (DEFAULTS_LIST_KEY, RECIPES_ENV_VAR, check_env, check_mentor_kwargs,
                                    check_recorded_algorithm, read_config_file)
from pe_rlhf.runtime.config_compose import RecipeSchema, check_overrides, compose_file, leaf_keys
from pe_rlhf.runtime.config_rules import ConfigError, invalid_value
from pe_rlhf.runtime.config_schema import OPEN_GROUPS  # free-form groups, checked by name in validate_baseline_config


# Each method's structured config (pe_rlhf.algorithms.baselines.config_schema,
# pe_rlhf.algorithms.baselines.imitation_schema).
SCHEMAS: dict[str, type] = {"sac_rs": SacRsConfig, "sac_lag": SacLagConfig, "ppo_rs": PpoRsConfig,
                            "ppo_lag": PpoLagConfig, "cpo": CpoConfig, "bc": BCConfig, "cql": CQLConfig,
                            "gail": GailConfig, "hg_dagger": HGDaggerConfig, "iwr": IWRConfig}


def _fields(schema: type, prefix: str = ""):
    """``(dotted name, dataclasses.Field)`` of every leaf field and open group, in declaration order."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        if dataclasses.is_dataclass(hints[f.name]):
            yield from _fields(hints[f.name], f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def rules(method: str) -> dict[str, Any]:
    """``{dotted field: rule}`` of ``method``'s schema, every field with a rule (``env`` has none), in its order."""
    return {name: f.metadata["rule"] for name, f in _fields(SCHEMAS[_method(method)])
            if "rule" in f.metadata}


def default_config(method: str) -> dict[str, Any]:
    """The paper's values for ``method`` as a plain dict (a new copy each call): its structured config's defaults."""
    return dataclasses.asdict(SCHEMAS[_method(method)]())


def _method(method: str) -> str:
    if method not in METHODS:
        raise invalid_value("method", method, f"allowed: {list(METHODS)}")
    return method


def profiles(method: str) -> dict[str, dict[str, Any]]:
    """``{profile name: overrides}`` for ``method`` (``paper``: none; ``cpu``: 30K env steps; ``smoke``: CI)."""
    _method(method)
    return copy.deepcopy(PROFILES[method])


@functools.cache
def recipe_schema(method: str) -> RecipeSchema:
    """``method``'s structured config as Hydra composes it: ``<method>_schema`` and its profiles."""
    _method(method)
    return RecipeSchema(f"{method}_schema", functools.partial(default_config, method), PROFILES[method], OPEN_GROUPS)


def recipe_config_path(method: str) -> Path | None:
    """``recipes/<method>/config.yaml``: under ``$PE_RLHF_RECIPES`` if set, else the first ``recipes/``
    found walking up from this file; None if neither (an installed package composes the schema alone)."""
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


def load_baseline_config(method: str, path: str | Path | None = None, overrides: Iterable[str] = (), *,
                         apply_profile: bool = True, validate: bool = True) -> DictConfig:
    """Schema <- recipe file <- profile <- overrides, composed by Hydra and validated (module docstring).

    ``apply_profile=False``: for a config written by :func:`~pe_rlhf.runtime.config.save_config` (a run's
    ``config.yaml``), whose values already include its profile and overrides (the profile is only recorded).
    """
    schema = recipe_schema(method)
    overrides = check_overrides(overrides, schema.profiles)
    path = Path(path) if path is not None else recipe_config_path(method)
    if path is None:
        cfg = compose_file(Path("<schema>"), overrides, {}, recipe=False, apply_profile=apply_profile, schema=schema)
    else:
        if not path.is_file():
            raise ConfigError(f"config file {str(path)!r} not found")
        values, recorded = read_config_file(path)
        check_recorded_algorithm(recorded, algorithm_name(method))
        recipe = DEFAULTS_LIST_KEY in values and apply_profile  # a Hydra primary config, not a run's saved one
        values = {k: v for k, v in values.items() if k != DEFAULTS_LIST_KEY}
        cfg = compose_file(path, overrides, values, recipe=recipe, apply_profile=apply_profile, schema=schema)
    if validate:
        validate_baseline_config(cfg, method)
    return cfg


# --------------------------------------------------------------------------- validation


def validate_baseline_config(cfg: DictConfig, method: str) -> None:
    """Check every field of ``method``'s config (its schema's rules), the env (as a DrivingConfig) and the
    fields that bound each other; raise :class:`ConfigError` naming the first bad field."""
    field_rules = rules(method)
    expected = set(field_rules) | {"env"}
    present = set(leaf_keys(OmegaConf.to_container(cfg)))
    for key in sorted(present - expected - set(OPEN_GROUPS)):
        raise ConfigError(f"unknown config key {key!r} for {method}; known: {sorted(expected)}", key)
    for key in sorted(field_rules):
        value = OmegaConf.select(cfg, key, default=_MISSING)
        if value is _MISSING:
            raise ConfigError(f"{key} is missing from the config", key)
        problem = field_rules[key](value)
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
        _check_imitation_relations(cfg, m.family)
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


def _check_imitation_relations(cfg: DictConfig, family: str) -> None:
    """The fields of an imitation config that bound each other (ConfigError naming the first bad one)."""
    data_steps = int(cfg.data.steps)
    o = cfg.optim
    if family == "offline":
        if o.batch_size > data_steps:
            raise invalid_value("optim.batch_size", o.batch_size, f"must be <= data.steps ({data_steps})")
        if o.updates_per_iteration > o.updates:
            raise invalid_value("optim.updates_per_iteration", o.updates_per_iteration,
                        f"must be <= optim.updates ({o.updates})")
    if family == "gail" and cfg.discriminator.batch_size > data_steps:
        raise invalid_value("discriminator.batch_size", cfg.discriminator.batch_size,
                    f"must be <= data.steps ({data_steps})")
    if family == "hil":
        check_mentor_kwargs(cfg.mentor)
        if o.batch_size > data_steps:
            raise invalid_value("optim.batch_size", o.batch_size, f"must be <= data.steps ({data_steps}): the first "
                        "round fits on the demonstrations")


def algorithm_name(method: str) -> str:
    """The registry name (:data:`pe_rlhf.algorithms.ALGORITHMS`) of the baseline ``method`` (``sac_rs`` ->
    ``sac-rs``), as its run folder records it."""
    return method.replace("_", "-")


def method_of(cfg: DictConfig) -> Method:
    """The :class:`Method` a validated config describes."""
    return METHODS[str(cfg.method)]


__all__ = ["IMITATION_FAMILIES", "METHODS", "OPEN_GROUPS", "PROFILE_NAMES", "SCHEMAS", "Method", "algorithm_name",
           "default_config", "load_baseline_config", "method_of", "profiles", "recipe_config_path", "recipe_schema",
           "rules", "validate_baseline_config"]
