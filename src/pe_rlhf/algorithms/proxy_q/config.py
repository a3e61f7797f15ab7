"""The proxy-Q recipes' configuration: compose a recipe's ``config.yaml`` with Hydra, validate every field.

``load_config(path, overrides)`` composes, each layer on top of the one before (Hydra's defaults list, see
:mod:`pe_rlhf.runtime.config_compose`):

1. the structured config :class:`~pe_rlhf.algorithms.proxy_q.config_schema.RecipeConfig` (the paper's values: the one
   place for each field's default, type and rule),
2. the recipe file (``path``, or ``recipes/pe_rlhf/config.yaml`` when found; may be partial),
3. the profile, a config group (:data:`~pe_rlhf.algorithms.proxy_q.config_profiles.PROFILES`; ``profile=cpu`` on the
   command line, else the file's ``defaults`` list, or the ``profile:`` of a file without one),
4. the overrides, Hydra's ``key=value`` (``["optim.lr=3e-4", "mentor.name=amateur"]``),

then :func:`validate_config`. Every group is closed: an unknown key fails naming it. Two groups are open by
design and checked by name instead: ``env`` (any :class:`~pe_rlhf.envs.config.DrivingConfig` field) and
``mentor.kwargs`` (arguments to ``make_mentor``): :mod:`pe_rlhf.runtime.config`, as for every recipe. Every error is a
:class:`~pe_rlhf.runtime.config_rules.ConfigError` (a ``ValueError``) that names the dotted field, the value and
what is allowed.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from pe_rlhf.runtime.config import (DEFAULTS_LIST_KEY, RECIPES_ENV_VAR, check_env, check_mentor_kwargs,
                                    check_recorded_algorithm, read_config_file)
from pe_rlhf.runtime.config_compose import check_overrides, compose_file, leaf_keys, override_key
from pe_rlhf.runtime.config_rules import ConfigError, invalid_value
from pe_rlhf.runtime.config_schema import OPEN_GROUPS
from pe_rlhf.algorithms.proxy_q.config_profiles import PROFILES
from pe_rlhf.algorithms.proxy_q.config_schema import (PROXY_Q, RULES, VARIANTS, default, defaults, variant_defaults,
                                                      variant_rules)
from pe_rlhf.algorithms.proxy_q.value_expert import parse_value_source

RECIPE_CONFIG = Path("pe_rlhf") / "config.yaml"  # relative to the recipes directory
PROXY_Q_ALGORITHMS = ("pe-rlhf", "haco", "haim-drl", "pvp")  # this recipe's methods, by registry name

# A person drives at a steady frame rate while the learner runs beside acting (see
# pe_rlhf.transforms.RealtimePacing, pe_rlhf.algorithms.proxy_q.background_updates); load_config applies these
# with mentor.name=human unless the fields are given, so the saved config shows the values used.
HUMAN_DEFAULTS: dict[str, Any] = {"collector.realtime_hz": 10.0, "optim.async_updates": True}


# --------------------------------------------------------------------------- loading


def default_config_path() -> Path | None:
    """The recipe's ``config.yaml``: under ``$PE_RLHF_RECIPES`` if set, else the first ``recipes/``
    found walking up from this file (a source checkout); None if neither (an installed package,
    which then composes the schema alone)."""
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


def load_config(path: str | Path | None = None, overrides: Iterable[str] = (), *,
                apply_profile: bool = True, validate: bool = True) -> DictConfig:
    """Schema <- recipe file <- profile <- overrides, composed by Hydra and validated (see the module docstring).

    ``path=None`` reads the recipe's ``config.yaml`` (:func:`default_config_path`), or composes the schema alone
    when there is none. ``overrides`` are Hydra's ``key=value`` strings (``loss.hidden=[128,128]``,
    ``selector.variance_threshold=null``). ``apply_profile=False`` skips step 3 (the profile is only recorded):
    for a config written by :func:`save_config`, whose values already include its profile and overrides.
    """
    overrides = check_overrides(overrides, PROXY_Q.profiles)
    path = Path(path) if path is not None else default_config_path()
    recorded = None  # the method a run's saved config records (read_config_file)
    if path is None:
        cfg = compose_file(Path("<schema>"), overrides, {}, recipe=False, apply_profile=apply_profile,
                           schema=PROXY_Q)
    else:
        if not path.is_file():
            raise ConfigError(f"config file {str(path)!r} not found")
        values, recorded = read_config_file(path)
        recipe = DEFAULTS_LIST_KEY in values and apply_profile  # a Hydra primary config, not a run's saved one
        values = {k: v for k, v in values.items() if k != DEFAULTS_LIST_KEY}
        if not recipe:
            values = retire_settings(values)
        cfg = compose_file(path, overrides, values, recipe=recipe, apply_profile=apply_profile, schema=PROXY_Q)
    cfg = finish_config(cfg, overrides, apply_human_defaults=apply_profile, validate=validate)
    if validate:
        check_recorded_algorithm(recorded, algorithm_name(cfg))
    return cfg


# Settings a run folder's saved config may hold from before they were retired (issue 43), each dropped on reading it:
# the selector's experiment options whose measurements lost (docs/results/claims/README.md), its Q-ensemble fit
# (now builders.ENSEMBLE_FIT), selector.enabled (physics.enabled says it), and the proxy-value loss's physics_labels,
# preactivation_penalty, label_physics_action, td_into_takeover and inverting_gradients (docs/experiments/learner.md).
# A run resumed from such a folder goes on under today's code.
RETIRED = ("selector.enabled", "selector.variance_threshold", "selector.switch_margin", "selector.veto_patience",
           "selector.imminent_failure", "selector.forecast_hold", "selector.forecast_hold_one_lane",
           "selector.forecast_recovery", "selector.warmup_selection", "selector.hidden", "selector.warmup_fit_steps",
           "selector.target_noise", "selector.tau", "selector.lr", "selector.batch_size", "loss.physics_labels",
           "loss.preactivation_penalty", "loss.label_physics_action", "loss.td_into_takeover",
           "loss.inverting_gradients", "loss.fused_critics", "loss.target_noise_clip", "collector.learning_starts",
           "collector.exploration")
# ... and those that moved: {old: new}
MOVED = {"loss.disturbance_weight": "disturbance.weight",
         "loss.num_disturbance_qvalue_nets": "disturbance.num_qvalue_nets"}


def retire_settings(values: dict[str, Any]) -> dict[str, Any]:
    """A saved config's values without the :data:`RETIRED` settings, the :data:`MOVED` ones where they are now
    (where the group they moved to is on; else dropped), the physics group's booleans as its two choices. Returns a
    new dict."""
    out = {group: dict(node) if isinstance(node, dict) else node for group, node in values.items()}
    physics = out.get("physics")
    if isinstance(physics, dict) and "use_idm" in physics:  # from before model/obstacles
        idm, mobil = physics.pop("use_idm", True), physics.pop("use_mobil", True)
        see, stop = physics.pop("see_obstacles", False), physics.pop("stop_for_obstacles", True)
        physics["model"] = "idm_mobil" if idm and mobil else "idm" if idm else "mobil"
        physics["obstacles"] = "avoid" if see else "stop" if stop else "blind"
    for key in (*RETIRED, *MOVED):
        group, name = key.split(".", 1)
        node = out.get(group)
        if not isinstance(node, dict) or name not in node:
            continue
        value = node.pop(name)
        target = MOVED.get(key)
        if target is not None:
            new_group, new_name = target.split(".", 1)
            if isinstance(out.get(new_group), dict) and out[new_group].get("enabled"):
                out[new_group].setdefault(new_name, value)
    return out


def complete_variants(cfg: DictConfig) -> None:
    """Each variant group (:data:`~pe_rlhf.algorithms.proxy_q.config_schema.VARIANTS`: ``selector`` by ``value``,
    ``loss`` by ``objective``, ``disturbance`` by ``enabled``) to exactly its chosen variant's settings, in its
    dataclass's order: a missing one at its default; another variant's one dropped where it holds that variant's
    default (a recipe file shows its default variant's settings, and ``loss.objective=proxy_value`` switches),
    refused where it does not (it would do nothing). Raises :class:`ConfigError` naming the field."""
    for group, spec in VARIANTS.items():
        node = OmegaConf.to_container(cfg[group]) if OmegaConf.select(cfg, group) is not None else {}
        if not isinstance(node, dict):
            raise invalid_value(group, node, "must be a group of settings")
        choice = node.get(spec.field, defaults()[group][spec.field])
        variant = _variant(group, choice)
        own = variant_defaults(group, variant)
        for name, value in node.items():
            if name in own:
                continue
            owners = [v for v in spec.classes if v != variant and name in variant_defaults(group, v)]
            if not owners:
                raise ConfigError(f"unknown config key '{group}.{name}'; the settings of {group}.{spec.field}="
                                  f"{_shown(choice)}: {list(own)}", f"{group}.{name}")
            if value != variant_defaults(group, owners[0])[name]:
                raise invalid_value(f"{group}.{name}", value, f"belongs to the {group} group's {_shown(owners[0])} "
                                    f"variant, and this config has {group}.{spec.field}={_shown(choice)}")
        with open_dict(cfg):
            cfg[group] = {name: node.get(name, value) for name, value in own.items()}
        OmegaConf.set_struct(cfg[group], True)


def _variant(group: str, choice: Any) -> Any:
    """The variant ``choice`` picks in ``group``, or :class:`ConfigError` naming the field and what is allowed."""
    spec = VARIANTS[group]
    try:
        variant = spec.pick(choice)
    except ValueError as err:
        raise invalid_value(f"{group}.{spec.field}", choice, str(err).split("; ", 1)[-1]) from None
    if not any(variant == v and type(variant) is type(v) for v in spec.classes):
        raise invalid_value(f"{group}.{spec.field}", choice, f"allowed: {[_shown(v) for v in spec.classes]}")
    return variant


def _shown(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def finish_config(cfg: DictConfig, overrides: Iterable[str] = (), *, apply_human_defaults: bool = True,
                  validate: bool = True) -> DictConfig:
    """What follows composition: each variant group completed (:func:`complete_variants`); with
    ``mentor.name=human``, :data:`HUMAN_DEFAULTS` for the fields neither ``overrides`` name nor the files set
    (skipped for a saved config, which holds its resolved values); then :func:`validate_config`. Returns ``cfg``,
    changed in place."""
    complete_variants(cfg)
    if apply_human_defaults:
        given = {override_key(item) for item in overrides}
        given |= {key for key in HUMAN_DEFAULTS if OmegaConf.select(cfg, key) != default(key)}
        _apply_human_defaults(cfg, given)
    if validate:
        validate_config(cfg)
    return cfg


def _apply_human_defaults(cfg: DictConfig, given: set[str]) -> None:
    """With ``mentor.name=human``, :data:`HUMAN_DEFAULTS` for the fields not given (a field counts as
    given when an override names it, or the file or profile sets it to a non-default value)."""
    if cfg.mentor.name != "human":
        return
    for key, value in HUMAN_DEFAULTS.items():
        if key not in given:
            OmegaConf.update(cfg, key, value)



# --------------------------------------------------------------------------- validation


_PROBE = "\0"  # a value every rule refuses (its message says what is allowed); a plain string rule accepts it


def reference_table() -> str:
    """The recipe config's fields as a Markdown table: field, default, what is allowed (each rule's own words).

    ``docs/guide/configuration.md`` holds this table (a test keeps them equal). ``env.*`` takes any
    ``DrivingConfig`` field and ``mentor.kwargs`` the mentor's arguments; their checks are listed below it. A
    variant group's fields follow the fixed ones, each variant's with its choice (``loss.gap_coef`` (objective=paper)).
    """
    rows = ["| field | default | allowed |", "|---|---|---|"]
    fields = [(f"`{field}`", rule, default(field)) for field, rule in RULES.items()]
    for group, spec in VARIANTS.items():
        for variant in spec.classes:
            values = variant_defaults(group, variant)
            fields += [(f"`{field}` ({group}: {_shown(variant)})", rule, values[field.split(".", 1)[1]])
                       for field, rule in variant_rules(group, variant).items()]
    for field, rule, default_value in fields:
        allowed = rule(_PROBE) or ("a non-empty string" + (", or null" if default_value is None else ""))
        shown = ("null" if default_value is None else str(default_value).lower() if isinstance(default_value, bool)
                 else default_value)
        rows.append(f"| {field} | `{shown}` | {allowed.replace('|', '/')} |")
    return "\n".join(rows)


def validate_config(cfg: DictConfig) -> None:
    """Check every field (:data:`RULES`), the env (as a DrivingConfig), the mentor's kwargs, and the
    fields that constrain each other; raise :class:`ConfigError` at the first problem."""
    rules = dict(RULES)
    for group, spec in VARIANTS.items():
        rules.update(variant_rules(group, _variant(group, OmegaConf.select(cfg, f"{group}.{spec.field}"))))
    for key in leaf_keys(OmegaConf.to_container(cfg)):
        if key not in rules and key not in OPEN_GROUPS:
            raise ConfigError(f"unknown config key {key!r}; known: {sorted(rules) + list(OPEN_GROUPS)}", key)
    for field, rule in rules.items():
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
    if c.backend == "single" and c.num_workers != 1:
        raise invalid_value("collector.num_workers", c.num_workers,
                    "the single backend runs one env: use 1, or collector.backend=multisync|multiasync")
    if cfg.mentor.name == "human" and c.backend != "single":
        raise invalid_value("collector.backend", c.backend,
                    "a human mentor drives one env in this process (one person, "
                    "one window): use single")
    if c.backend in ("multisync", "ray") and c.frames_per_batch % c.num_workers:
        raise invalid_value("collector.frames_per_batch", c.frames_per_batch,
                    f"must be divisible by collector.num_workers ({c.num_workers}): with collector.backend="
                    f"{c.backend} each worker collects an equal share of every batch")
    if c.backend != "single":
        for field, value in (("collector.realtime_hz", c.realtime_hz),
                             ("optim.async_updates", cfg.optim.async_updates)):
            if value:
                raise invalid_value(field, value,
                            f"needs collector.backend=single (got {c.backend}): the pacing and the "
                            "background learner drive one env in this process; use 0 / false")
    if c.warmup_policy is not None and c.warmup_steps < 1:
        raise invalid_value("collector.warmup_policy", c.warmup_policy,
                    "drives the warm-up, but collector.warmup_steps is 0: give the warm-up steps, or null")
    method_name(cfg)  # the loss and the disturbance critic
    if cfg.physics.enabled and parse_value_source(cfg.selector.value)[0] == "warmup" and c.warmup_steps < 1:
        raise invalid_value("collector.warmup_steps", c.warmup_steps,
                            "must be >= 1 with selector.value=warmup (the Q-ensemble is fitted on warm-up data)")


# --------------------------------------------------------------------------- views


def method_name(cfg: DictConfig) -> str:
    """``"PE-RLHF"`` (``physics.enabled``), ``"HACO"`` (without physics) or ``"HAIM-DRL"`` (HACO with
    ``disturbance.enabled``; PE-RLHF with it is ``"PE-RLHF+disturbance"``), ``"PVP"`` (without physics, with
    ``loss.objective=proxy_value``).

    With ``physics.enabled`` physics proposes and the selector picks during a takeover (the paper's "w/o ensemble"
    ablation is ``selector.num_members=1``, its physics ablations ``physics.model=idm`` / ``mobil``).
    """
    physics = bool(cfg.physics.enabled)
    disturbance = bool(cfg.disturbance.enabled)
    if str(OmegaConf.select(cfg, "loss.objective", default="paper")) == "proxy_value":
        if disturbance:
            raise invalid_value("disturbance.enabled", True, "needs loss.objective=paper (HAIM-DRL's disturbance "
                                "critic is a PERLHFLoss term)")
        if not physics:
            return "PVP"
    if physics:
        return "PE-RLHF+disturbance" if disturbance else "PE-RLHF"
    return "HAIM-DRL" if disturbance else "HACO"


def algorithm_name(cfg: DictConfig) -> str:
    """The registry name (:data:`pe_rlhf.algorithms.ALGORITHMS`) of the method ``cfg`` describes, as a run records
    it: ``pe-rlhf``, ``haco``, ``haim-drl`` or ``pvp`` (PE-RLHF with the disturbance critic is a ``pe-rlhf`` run)."""
    return method_name(cfg).removesuffix("+disturbance").lower()


def physics_config(cfg: DictConfig):
    """The :class:`~pe_rlhf.physics.policy.PhysicsConfig` of ``cfg.physics`` (paper IDM/MOBIL parameters)."""
    from pe_rlhf.physics.policy import PhysicsConfig

    p = cfg.physics
    return PhysicsConfig(see_obstacles=p.obstacles == "avoid", stop_for_obstacles=p.obstacles != "blind",
                         use_idm=p.model != "mobil", use_mobil=p.model != "idm")


__all__ = ["HUMAN_DEFAULTS", "PROFILES", "PROXY_Q_ALGORITHMS", "RULES", "algorithm_name", "default_config_path",
           "finish_config", "load_config", "method_name", "physics_config", "reference_table", "validate_config"]
