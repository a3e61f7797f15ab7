"""What a ``--resume DIR key=value ...`` changes: each changed setting is applied, or refused in one line naming it.

A resumed run is built from the run folder's ``config.yaml`` with the command line's overrides, then loads its
checkpoint. Most settings take effect from there (the learner is built anew from the config; optimiser
hyper-parameters are put back over the checkpoint's, :func:`optimizer_settings`); some cannot, because the
checkpoint's state would silently override them (the RNG streams of ``seed``, a mentor's state) or the saved data
was cut by them (the journal's batch size). A family names those in a table ``{dotted key or prefix: why}`` (a
value may also be a function of ``(was, now)`` returning the reason, or None to apply it);
:func:`announce_changes` prints ``resume: key was -> now (applied)`` for the others and raises a
:class:`~pe_rlhf.runtime.config_rules.ConfigError` naming the first refused one. Nothing is ignored silently.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pe_rlhf.runtime.config_rules import ConfigError

Refusal = str | Callable[[Any, Any], str | None]

__all__ = ["announce_changes", "changed_settings", "optimizer_settings", "restore_optimizer_settings"]


def _flat(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, Mapping):
        out = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: node}


def changed_settings(saved: DictConfig, now: DictConfig) -> list[tuple[str, Any, Any]]:
    """``(dotted key, saved value, new value)`` for every leaf that differs (added or removed ones too)."""
    a = _flat(OmegaConf.to_container(saved, resolve=True))
    b = _flat(OmegaConf.to_container(now, resolve=True))
    return [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def announce_changes(saved: DictConfig, now: DictConfig, refused: Mapping[str, Refusal], run: str) -> list[str]:
    """Print and return one ``resume: ... (applied)`` line per changed setting; ConfigError naming the first one
    ``refused`` (key or prefix) refuses, with its reason."""
    lines = []
    for key, was, value in changed_settings(saved, now):
        rule = next((why for prefix, why in refused.items() if key == prefix or key.startswith(prefix + ".")), None)
        reason = rule(was, value) if callable(rule) else rule
        if reason:
            raise ConfigError(f"--resume {run} {key}={value!r}: a resume cannot change {key} (the run has {was!r}): "
                              f"{reason}; resume without it, or start a new run with --out", key)
        lines.append(f"resume: {key} {was!r} -> {value!r} (applied)")
    for line in lines:
        print(line, flush=True)
    return lines


def optimizer_settings(optimizers: Mapping[str, Any]) -> dict[str, list[dict]]:
    """Each optimiser's parameter-group hyper-parameters (``lr``, ``betas``, ...: all but ``params``)."""
    return {name: [{k: v for k, v in g.items() if k != "params"} for g in opt.param_groups]
            for name, opt in optimizers.items()}


def restore_optimizer_settings(optimizers: Mapping[str, Any], settings: dict[str, list[dict]]) -> None:
    """Put :func:`optimizer_settings` back (after a checkpoint's optimiser state restored the saved ones)."""
    for name, groups in settings.items():
        for group, saved in zip(optimizers[name].param_groups, groups):
            group.update(saved)
