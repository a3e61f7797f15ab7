"""The field rules every recipe config uses: each takes a value and says what is allowed (None when the value is fine).

A rule's message is the "what is allowed" half of a :class:`ConfigError` (``optim.lr=-1 is invalid: must be a finite
number > 0``); :func:`invalid_value` builds the whole error. The fields that use them are declared, with their
defaults, in each family's structured config (:mod:`pe_rlhf.algorithms.proxy_q.config_schema` for the proxy-Q recipes,
:mod:`pe_rlhf.algorithms.baselines.config_schema` and :mod:`pe_rlhf.algorithms.baselines.imitation_schema`), through
:mod:`pe_rlhf.runtime.config_schema`; a rule of one family's fields alone lives in that family's schema.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from pe_rlhf.envs.splits import SPLITS as SCENE_SPLITS

# The logger group's backends (pe_rlhf.runtime.metrics_logger.MetricsLogger); csv writes metrics.csv, which the run's
# plots, --resume (it is cut back to the checkpoint) and the summaries (pe-rlhf compare, a sweep's plots) read.
LOGGER_BACKENDS = ("csv", "wandb", "tensorboard", "mlflow")
SPLITS = tuple(SCENE_SPLITS)
IMPORT_PATH = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*$")


class ConfigError(ValueError):
    """An invalid configuration value; ``field`` is the dotted name (``optim.lr``) when known."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


def invalid_value(field: str, value: Any, allowed: str) -> ConfigError:
    if isinstance(value, (DictConfig, ListConfig)):
        value = OmegaConf.to_container(value)
    return ConfigError(f"{field}={value!r} is invalid: {allowed}", field)



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


def rule_backends(v) -> str | None:
    ok = (isinstance(v, (list, tuple, ListConfig)) and all(isinstance(b, str) and b in LOGGER_BACKENDS for b in v)
          and len(set(v)) == len(v) and "csv" in v)
    return None if ok else (f"must be a list of distinct backends from {list(LOGGER_BACKENDS)} that holds csv "
                            "(metrics.csv: the plots, --resume and the summaries read it)")


def rule_hidden(v) -> str | None:
    ok = isinstance(v, (list, tuple, ListConfig)) and len(v) > 0 and all(
        isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in v)
    return None if ok else "must be a non-empty list of positive integers (layer widths), e.g. [256, 256]"


def rule_target_entropy(v) -> str | None:
    return None if v == "auto" or rule_number()(v) is None else "must be 'auto' (= -dim(action)) or a finite number"


def rule_mentor_name(v) -> str | None:
    from pe_rlhf.mentors.registry import MENTOR_NAMES

    if isinstance(v, str) and (v in MENTOR_NAMES or IMPORT_PATH.match(v)):
        return None
    return f"allowed: {list(MENTOR_NAMES)} or a 'package.module:ClassName' import path"


def rule_window_size(v) -> str | None:
    ok = isinstance(v, (list, tuple, ListConfig)) and len(v) == 2 and all(rule_int(1)(x) is None for x in v)
    return None if ok else "must be [width, height] in pixels"


# HumanMentor arguments a YAML value can give (mapping / input_state are objects, for code only).
HUMAN_KWARGS: dict[str, Rule] = {"fps": rule_number(0), "scaling": rule_number(0, lo_open=True), "title": rule_string,
                                 "size": rule_window_size, "on_disconnect": rule_choice("agent", "pause")}


def check_human_kwargs(kwargs: DictConfig) -> None:
    for key in kwargs:
        if key not in HUMAN_KWARGS:
            raise invalid_value(f"mentor.kwargs.{key}", kwargs[key],
                        f"unknown HumanMentor argument; known: {sorted(HUMAN_KWARGS)}")
        problem = HUMAN_KWARGS[key](kwargs[key])
        if problem is not None:
            raise invalid_value(f"mentor.kwargs.{key}", kwargs[key], problem)

