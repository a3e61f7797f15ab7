"""The config pieces every recipe shares: where recipes are, a run's saved ``config.yaml``, the env and mentor checks.

Each family composes and validates its own config (:mod:`pe_rlhf.algorithms.proxy_q.config` for PE-RLHF, HACO and
HAIM-DRL, :mod:`pe_rlhf.algorithms.baselines.config` for the baselines), over :mod:`pe_rlhf.runtime.config_compose`;
both read and write a run folder's ``config.yaml`` here (:func:`save_config`, :func:`read_config_file`: the method's
registry name under :data:`ALGORITHM_KEY`), check the open groups ``env`` (:func:`check_env`: any
:class:`~pe_rlhf.envs.config.DrivingConfig` field) and ``mentor.kwargs`` (:func:`check_mentor_kwargs`), and build
the world's :class:`~pe_rlhf.envs.config.DrivingConfig` (:func:`driving_config`). Every error is a
:class:`~pe_rlhf.runtime.config_rules.ConfigError` naming the dotted field.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pe_rlhf import durable
from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.runtime.config_retired import translate_retired
from pe_rlhf.runtime.config_rules import ConfigError, check_human_kwargs, invalid_value, rule_bool, rule_number

RECIPES_ENV_VAR = "PE_RLHF_RECIPES"  # the recipes directory, where no recipes/ is found above the package
# A run's saved config.yaml records the run's method by its registry name (pe_rlhf.algorithms.ALGORITHMS) under
# this top-level key; the loaders read it apart from the config values and check it against them.
ALGORITHM_KEY = "algorithm"
DEFAULTS_LIST_KEY = "defaults"  # a Hydra primary config's defaults list


def parse_overrides(overrides: Iterable[str]) -> list[tuple[str, str]]:
    """``key=value`` strings as ``(key, value)`` pairs (the baselines' loader; values in YAML syntax)."""
    if isinstance(overrides, str):  # a lone "a=b" would otherwise be iterated character by character
        overrides = [overrides]
    parsed = []
    for item in overrides:
        if not isinstance(item, str) or "=" not in item or not item.split("=", 1)[0].strip():
            raise ConfigError(f"override {item!r} is not of the form key=value (e.g. optim.lr=3e-4)")
        key, value = item.split("=", 1)
        parsed.append((key.strip(), value))
    return parsed


def read_config_file(path: str | Path) -> tuple[dict[str, Any], str | None]:
    """A config file's values, and apart from them the registry name a run recorded under :data:`ALGORITHM_KEY`
    (None: a recipe's config, or a run folder written before runs recorded it). Settings an older run saved that
    are no longer settings come back as the ones that replaced them
    (:func:`~pe_rlhf.runtime.config_retired.translate_retired`)."""
    values = OmegaConf.to_container(OmegaConf.load(path))
    if values is None:
        values = {}
    if not isinstance(values, dict):
        raise ConfigError(f"config file {path} must be a mapping of config groups, got {type(values).__name__}")
    recorded = values.pop(ALGORITHM_KEY, None)
    return translate_retired(values, path), None if recorded is None else str(recorded)


def check_recorded_algorithm(recorded: str | None, expected: str) -> None:
    """Refuse a saved config whose recorded method is not the one its values describe (e.g. a HACO run folder
    resumed with ``physics.enabled=true``)."""
    if recorded is not None and recorded != expected:
        raise invalid_value(ALGORITHM_KEY, recorded, f"the run folder's config describes {expected!r}; resume a "
                            "run with the values it was started with")


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
        check_human_kwargs(mentor.kwargs)
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


def driving_config(cfg: DictConfig, **changes: Any) -> DrivingConfig:
    """The :class:`DrivingConfig` of ``cfg.env``, with ``changes`` on top (e.g. ``split="test"`` for eval)."""
    values = {**OmegaConf.to_container(cfg.env, resolve=True), **changes}
    check_env(OmegaConf.create(values))
    return DrivingConfig.from_dict(values)


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
    durable.replace_bytes(path, OmegaConf.to_yaml(cfg, resolve=True).encode())  # atomic, never through a symlink
    return path


__all__ = ["ALGORITHM_KEY", "DEFAULTS_LIST_KEY", "RECIPES_ENV_VAR", "check_env", "check_mentor_kwargs",
           "check_recorded_algorithm", "driving_config", "parse_overrides", "read_config_file", "save_config",
           "to_container"]
