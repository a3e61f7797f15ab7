"""What every recipe's structured config is built of: a field with its default and rule, an open group, the
``logger`` group and the ``actor_selection`` group.

Each family declares its config as dataclasses of :func:`knob` fields (:mod:`pe_rlhf.algorithms.proxy_q.config_schema`
for PE-RLHF, HACO and HAIM-DRL; :mod:`pe_rlhf.algorithms.baselines.config_schema` and
:mod:`pe_rlhf.algorithms.baselines.imitation_schema` for the baselines), each field's rule from
:mod:`pe_rlhf.runtime.config_rules`; :class:`LoggerConfig` is the ``logger`` group they all share (what
:class:`~pe_rlhf.runtime.metrics_logger.MetricsLogger` takes).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

from pe_rlhf.runtime.config_rules import Rule, rule_backends, rule_int, rule_string

OPEN_GROUPS = ("env", "mentor.kwargs")  # free-form groups, checked by name after composition


def knob(default: Any, rule: Rule) -> Any:
    """A config field: its default and its rule (``field.metadata["rule"]``)."""
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: copy.deepcopy(default), metadata={"rule": rule})
    return field(default=default, metadata={"rule": rule})


def open_group(default: dict[str, Any], rule: Rule | None = None) -> Any:
    """A free-form group (any key; checked by name in :func:`~pe_rlhf.algorithms.proxy_q.config.validate_config`), with
    ``rule`` for the group as a whole if given."""
    metadata = {"open": True} if rule is None else {"open": True, "rule": rule}
    return field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)


@dataclass
class LoggerConfig:
    """Where the metrics go (:class:`~pe_rlhf.runtime.metrics_logger.MetricsLogger`); the run folder is --out DIR."""

    # csv (metrics.csv, always: the plots, --resume and the summaries read it) + any of wandb (offline unless
    # $WANDB_MODE says otherwise), tensorboard, mlflow ($MLFLOW_TRACKING_URI, else <run folder>/mlruns)
    backends: list[str] = knob(["csv"], rule_backends)
    project: str = knob("pe-rlhf", rule_string)  # wandb's project, MLflow's experiment
    log_every: int = knob(1, rule_int(1))  # iterations between log lines


@dataclass
class ActorSelectionConfig:
    """Picking the run's actor on train scenes (:mod:`pe_rlhf.runtime.actor_selection`); never on the test scenes,
    which are for the final evaluation."""

    every_frames: int = knob(0, rule_int(0))  # 0: the last actor is the run's actor
    episodes: int = knob(50, rule_int(1))  # the first this many train scenes (50: all of them)


__all__ = ["OPEN_GROUPS", "ActorSelectionConfig", "LoggerConfig", "knob", "open_group"]
