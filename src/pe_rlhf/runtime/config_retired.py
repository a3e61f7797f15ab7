"""Settings an older run's saved ``config.yaml`` may hold that are no longer settings, and what each becomes.

Issue 43 retired, for every recipe: ``logger.csv`` / ``wandb`` / ``tensorboard`` / ``mlflow`` (now the list
``logger.backends``, which always holds ``csv``), ``logger.wandb_project`` (now ``logger.project``),
``logger.wandb_mode`` (now wandb's own ``$WANDB_MODE``, offline when unset), ``logger.out_dir`` (the run folder is
``--out DIR``), ``mentor.seed`` (the mentor is seeded from the run's ``seed``) and ``actor_selection.split`` (always
the train scenes). :func:`translate_retired` rewrites a config file's values to the settings that replaced them, so
that ``--resume`` and the loaders of a run folder read old run folders; a value the new settings cannot express is
refused in one line (:class:`~pe_rlhf.runtime.config_rules.ConfigError`), one they no longer need is dropped with a
warning that says what the run does instead.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from pe_rlhf.runtime.config_rules import LOGGER_BACKENDS, ConfigError, invalid_value

_SWITCHES = LOGGER_BACKENDS  # the retired logger.<backend>: true|false switches, one per backend
_BACKENDS = "logger.backends lists the loggers (csv always, e.g. [csv, wandb])"
# {retired key: what took its place}: an override that names one is refused with this (check_retired_override).
RETIRED: dict[str, str] = {
    **{f"logger.{name}": _BACKENDS for name in _SWITCHES},
    "logger.wandb_project": "logger.project",
    "logger.wandb_mode": "wandb's own $WANDB_MODE (offline when unset)",
    "logger.out_dir": "the run folder is --out DIR",
    "mentor.seed": "the mentor is seeded from the run's seed (worker i: seed + i)",
    "actor_selection.split": "the actor is picked on train scenes only",
}


def translate_retired(values: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """``values`` (a config file's, read from ``path``) with the retired settings translated, changed in place."""
    if isinstance(values.get("logger"), dict):
        _translate_logger(values["logger"], Path(path))
    mentor = values.get("mentor")
    if isinstance(mentor, dict) and "seed" in mentor:
        seed, run_seed = mentor.pop("seed"), values.get("seed", 0)
        if seed != run_seed:
            warnings.warn(f"{path}: mentor.seed={seed!r} is no longer a setting: the mentor is seeded from "
                          f"seed={run_seed!r} (a resumed run continues its mentor from the checkpoint)", UserWarning,
                          stacklevel=3)
    picking = values.get("actor_selection")
    if isinstance(picking, dict) and "split" in picking:
        split = picking.pop("split")
        if split != "train":
            raise invalid_value("actor_selection.split", split, f"no longer a setting (in {path}): the actor is "
                                "picked on train scenes only; delete the line")
    return values


def check_retired_override(key: str, value: str) -> None:
    """Refuse a ``key=value`` override that names a retired setting, in one line saying what took its place."""
    if key in RETIRED:
        raise ConfigError(f"{key}={value} is invalid: no longer a setting: {RETIRED[key]}", key)


def _translate_logger(logger: dict[str, Any], path: Path) -> None:
    switches = {name: logger.pop(name) for name in _SWITCHES if name in logger}
    if switches and "backends" not in logger:  # csv always: the plots, --resume and the summaries read metrics.csv
        logger["backends"] = ["csv"] + [name for name in _SWITCHES[1:] if switches.get(name) is True]
    if "wandb_project" in logger:
        project = logger.pop("wandb_project")
        logger.setdefault("project", project)
    mode = logger.pop("wandb_mode", "offline")
    if mode != "offline" and "wandb" in logger.get("backends", ()):
        warnings.warn(f"{path}: logger.wandb_mode={mode!r} is no longer a setting: wandb's mode is $WANDB_MODE "
                      "(offline when unset)", UserWarning, stacklevel=4)
    out_dir = logger.pop("out_dir", None)
    if out_dir is not None and Path(out_dir).resolve() != path.resolve().parent:
        raise invalid_value("logger.out_dir", out_dir, f"no longer a setting (in {path}): the run folder is --out "
                            "DIR; delete the line")


__all__ = ["RETIRED", "check_retired_override", "translate_retired"]
