"""A sweep config (YAML) read and checked into a :class:`SweepSpec`; every error names the field.

    name: epsilon_sensitivity            # optional (default: the file's stem); names OUT by default
    description: ...                     # optional, copied into summary.md
    base: [profile=cpu]                  # recipe overrides for every cell (list of key=value, or a mapping)
    methods: [pe-rlhf, haco]             # built-in names (pe_rlhf.apps.sweeps.methods), or mappings:
      # - {name: haco-lanes, method: haco, overrides: [env.lane_features=true]}   (a variant of a built-in)
      # - {name: sac-rs-fast, recipe: sac_rs, overrides: [...], mentor_key: null}  (from a recipe entry)
    mentors: [professional, amateur]     # optional axis: names, or {label, name, kwargs}
    seeds: [0, 1, 2]
    parameters:                          # optional axis: key -> values, crossed over the keys
      selector.epsilon_select: [0, 0.25, 0.5]
    variants:                            # optional axis: label -> overrides (crossed with parameters)
      idm_only: [physics.model=idm]
    metrics: [success_rate, safety_violation]   # columns of summary.md (pe_rlhf.apps.sweeps.metrics.METRICS)
    resources: {num_cpus: 1}             # per cell (Ray task); torch runs that many threads
    shield: 0.5                          # optional: also evaluate each trained cell's actor under the runtime
                                         # shield (threshold in seconds; true: the default), shielded_eval.json

The grid is method x mentor x parameter x seed; a method without a mentor (``mentor_key: null``, e.g.
``idm-mobil``) skips the mentor axis, one with ``parameters: false`` the parameter axis.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pe_rlhf.apps.sweeps.methods import MethodSpec, builtin_methods, recipe_names

TOP_LEVEL = ("name", "description", "base", "methods", "mentors", "seeds", "parameters", "variants", "metrics",
             "resources", "shield")
METHOD_FIELDS = ("name", "method", "recipe", "policy", "overrides", "mentor_key", "parameters")
MENTOR_FIELDS = ("label", "name", "kwargs")
RESOURCE_FIELDS = ("num_cpus",)
_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+=-]*$")
_KEY = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


class SweepConfigError(ValueError):
    """An invalid sweep config; ``field`` is the dotted / indexed field (``methods[1].recipe``)."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class MentorSpec:
    """One value of the mentor axis: ``label`` (row label, cell-name part), registry ``name``, ``kwargs``."""

    label: str
    name: str
    kwargs: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class Variant:
    """One value of the parameter axis: ``label``, the recipe ``overrides`` it adds, and ``values``
    (``(key, value)`` of the ``parameters`` grid, for plotting against; empty for named variants)."""

    label: str
    overrides: tuple[str, ...]
    values: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class SweepSpec:
    """A checked sweep config (see the module docstring); ``mentors`` / ``variants`` empty: no such axis."""

    name: str
    base: tuple[str, ...]
    methods: tuple[MethodSpec, ...]
    seeds: tuple[int, ...]
    mentors: tuple[MentorSpec, ...] = ()
    variants: tuple[Variant, ...] = ()
    metrics: tuple[str, ...] = ()
    num_cpus: float = 1.0
    description: str = ""
    shield: float | None = None  # [s]: each trained cell's actor is also evaluated under the runtime shield

    @property
    def parameter_keys(self) -> tuple[str, ...]:
        """The ``parameters`` keys (empty with named variants only): the x axis of the summary plot."""
        return tuple(k for k, _ in self.variants[0].values) if self.variants else ()


def _fail(field: str, value: Any, allowed: str) -> SweepConfigError:
    return SweepConfigError(f"sweep config: {field}={value!r} is invalid: {allowed}", field)


def yaml_value(value: Any) -> str:
    """``value`` as the right-hand side of a recipe override (YAML): ``true``, ``null``, ``0.25``, ``[1, 2]``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return value if re.fullmatch(r"[\w.:/+-]+", value) else json.dumps(value)
    return json.dumps(value)


def _overrides(value: Any, field: str) -> tuple[str, ...]:
    """``[key=value, ...]`` or a (nested) mapping -> ``("key=value", ...)``."""
    if value is None:
        return ()
    if isinstance(value, Mapping):
        flat: list[str] = []
        for key, item in value.items():
            if not isinstance(key, str) or not _KEY.match(key):
                raise _fail(f"{field}.{key}", item, "keys must be dotted config names (e.g. optim.lr)")
            if isinstance(item, Mapping) and item:
                flat.extend(f"{key}.{o}" for o in _overrides(item, f"{field}.{key}"))
            else:
                flat.append(f"{key}={yaml_value(item)}")
        return tuple(flat)
    if not isinstance(value, list):
        raise _fail(field, value, "must be a list of key=value overrides or a mapping")
    for i, item in enumerate(value):
        if not isinstance(item, str) or "=" not in item or not _KEY.match(item.split("=", 1)[0].strip()):
            raise _fail(f"{field}[{i}]", item, "must be a key=value override (e.g. optim.lr=3e-4)")
    return tuple(item.strip() for item in value)


def _label(value: Any, field: str) -> str:
    if not isinstance(value, str) or not _LABEL.match(value):
        raise _fail(field, value, "must be a label of letters, digits and . _ + = - (a folder name part)")
    return value


def _method(item: Any, i: int, builtins: dict[str, MethodSpec]) -> MethodSpec:
    field = f"methods[{i}]"
    if isinstance(item, str):
        if item not in builtins:
            raise _fail(field, item, f"unknown method; built-in: {sorted(builtins)}, or a mapping with a recipe")
        return builtins[item]
    if not isinstance(item, Mapping):
        raise _fail(field, item, "must be a built-in method name or a mapping")
    unknown = sorted(set(item) - set(METHOD_FIELDS))
    if unknown:
        raise _fail(f"{field}.{unknown[0]}", item[unknown[0]], f"unknown field; known: {list(METHOD_FIELDS)}")
    name = _label(item.get("name"), f"{field}.name")
    start = item.get("method", name if name in builtins else None)
    if start is not None and start not in builtins:
        raise _fail(f"{field}.method", start, f"allowed: {sorted(builtins)}")
    spec = builtins[start] if start is not None else None
    recipe = item.get("recipe", spec.recipe if spec else None)
    if recipe not in recipe_names():
        raise _fail(f"{field}.recipe", recipe, f"allowed: {list(recipe_names())} (or give a built-in 'method')")
    if spec is None or recipe != spec.recipe:
        spec = MethodSpec(name, recipe, mentor_key=None if recipe == "evaluate" else "mentor.name",
                          parameters=recipe != "evaluate")
    policy = item.get("policy", spec.policy)
    if recipe == "evaluate" and not isinstance(policy, str):
        raise _fail(f"{field}.policy", policy, "an evaluate method needs a registered policy name (e.g. idm-mobil)")
    mentor_key = item.get("mentor_key", spec.mentor_key)
    if mentor_key is not None and not (isinstance(mentor_key, str) and _KEY.match(mentor_key)):
        raise _fail(f"{field}.mentor_key", mentor_key, "must be a dotted config key (e.g. mentor.name) or null")
    parameters = item.get("parameters", spec.parameters)
    if not isinstance(parameters, bool):
        raise _fail(f"{field}.parameters", parameters, "must be true or false")
    extra = _overrides(item.get("overrides"), f"{field}.overrides")
    return replace(spec, name=name, recipe=recipe, policy=policy, overrides=spec.overrides + extra,
                   mentor_key=mentor_key, parameters=parameters)


def _mentor(item: Any, i: int) -> MentorSpec:
    field = f"mentors[{i}]"
    if isinstance(item, str):
        return MentorSpec(_label(item, field), item)
    if not isinstance(item, Mapping):
        raise _fail(field, item, "must be a mentor name or a mapping {label, name, kwargs}")
    unknown = sorted(set(item) - set(MENTOR_FIELDS))
    if unknown:
        raise _fail(f"{field}.{unknown[0]}", item[unknown[0]], f"unknown field; known: {list(MENTOR_FIELDS)}")
    name = item.get("name")
    if not isinstance(name, str) or not name:
        raise _fail(f"{field}.name", name, "must be a mentor name (professional, amateur, adversarial, collapsing, "
                    "...)")
    kwargs = item.get("kwargs") or {}
    if not isinstance(kwargs, Mapping) or not all(isinstance(k, str) and _KEY.match(k) for k in kwargs):
        raise _fail(f"{field}.kwargs", kwargs, "must be a mapping of argument names to values")
    return MentorSpec(_label(item.get("label", name), f"{field}.label"), name, tuple(sorted(kwargs.items())))


def _seeds(value: Any) -> tuple[int, ...]:
    ok = isinstance(value, list) and value and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                                                    for s in value)
    if not ok:
        raise _fail("seeds", value, "must be a non-empty list of integers >= 0")
    if len(set(value)) != len(value):
        raise _fail("seeds", value, "must not repeat a seed")
    return tuple(value)


def _fmt(value: Any) -> str:
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return str(int(value)) if not math.isinf(value) else repr(value)
    return yaml_value(value).strip('"').replace(" ", "")


def _variants(parameters: Any, variants: Any) -> tuple[Variant, ...]:
    grid: list[Variant] = []
    if parameters is not None:
        if not isinstance(parameters, Mapping) or not parameters:
            raise _fail("parameters", parameters, "must be a mapping of config keys to lists of values")
        keys = list(parameters)
        for key in keys:
            values = parameters[key]
            if not isinstance(key, str) or not _KEY.match(key):
                raise _fail(f"parameters.{key}", values, "keys must be dotted config names")
            if not isinstance(values, list) or not values:
                raise _fail(f"parameters.{key}", values, "must be a non-empty list of values")
        short = {k: k.rsplit(".", 1)[-1] for k in keys}
        if len(set(short.values())) < len(keys):  # two keys ending alike: label by the full key
            short = {k: k for k in keys}
        for combo in itertools.product(*(parameters[k] for k in keys)):
            label = "+".join(f"{short[k]}={_fmt(v)}" for k, v in zip(keys, combo))
            grid.append(Variant(label, tuple(f"{k}={yaml_value(v)}" for k, v in zip(keys, combo)),
                                tuple(zip(keys, combo))))
    named: list[Variant] = []
    if variants is not None:
        if not isinstance(variants, Mapping) or not variants:
            raise _fail("variants", variants, "must be a mapping of labels to override lists")
        for label, overrides in variants.items():
            named.append(Variant(_label(label, f"variants.{label}"), _overrides(overrides, f"variants.{label}")))
    if grid and named:
        return tuple(Variant(f"{n.label}+{g.label}", n.overrides + g.overrides, g.values) for n in named for g in grid)
    return tuple(grid or named)


def _shield(value: Any) -> float | None:
    """The ``shield`` field: None / false (no shielded evaluation), true (the shield's default threshold) or a
    threshold in seconds >= 0."""
    if value is None or value is False:
        return None
    if value is True:
        from pe_rlhf.transforms.shield import DEFAULT_THRESHOLD

        return float(DEFAULT_THRESHOLD)
    if isinstance(value, (int, float)) and math.isfinite(value) and value >= 0:
        return float(value)
    raise _fail("shield", value, "a threshold in seconds >= 0 (e.g. 0.5), true (the default threshold) or false")


def parse_sweep(raw: Any, default_name: str = "sweep") -> SweepSpec:
    """A checked :class:`SweepSpec` from a loaded YAML mapping; raises :class:`SweepConfigError`."""
    from pe_rlhf.apps.sweeps.metrics import DEFAULT_METRICS, METRICS

    if not isinstance(raw, Mapping):
        raise SweepConfigError(f"sweep config must be a mapping of fields, got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(TOP_LEVEL))
    if unknown:
        raise _fail(unknown[0], raw[unknown[0]], f"unknown field; known: {list(TOP_LEVEL)}")
    name = _label(raw.get("name", default_name), "name")
    methods_raw = raw.get("methods")
    if not isinstance(methods_raw, list) or not methods_raw:
        raise _fail("methods", methods_raw, "must be a non-empty list of methods")
    builtins = builtin_methods()
    methods = tuple(_method(m, i, builtins) for i, m in enumerate(methods_raw))
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise _fail("methods", names, "method names must be unique")
    mentors_raw = raw.get("mentors")
    if mentors_raw is not None and (not isinstance(mentors_raw, list) or not mentors_raw):
        raise _fail("mentors", mentors_raw, "must be a non-empty list (or left out: the recipes' own mentor)")
    mentors = tuple(_mentor(m, i) for i, m in enumerate(mentors_raw or []))
    if len({m.label for m in mentors}) != len(mentors):
        raise _fail("mentors", [m.label for m in mentors], "mentor labels must be unique (give each a label)")
    metrics = raw.get("metrics", list(DEFAULT_METRICS))
    if not isinstance(metrics, list) or not metrics or any(m not in METRICS for m in metrics):
        raise _fail("metrics", metrics, f"must be a non-empty list of {sorted(METRICS)}")
    resources = raw.get("resources") or {}
    if not isinstance(resources, Mapping) or set(resources) - set(RESOURCE_FIELDS):
        raise _fail("resources", resources, f"must be a mapping with {list(RESOURCE_FIELDS)}")
    num_cpus = resources.get("num_cpus", 1)
    if isinstance(num_cpus, bool) or not isinstance(num_cpus, (int, float)) or not 0 < num_cpus < 1e4:
        raise _fail("resources.num_cpus", num_cpus, "must be a number > 0 (CPUs per cell)")
    description = raw.get("description", "")
    if not isinstance(description, str):
        raise _fail("description", description, "must be a string")
    return SweepSpec(name=name, base=_overrides(raw.get("base"), "base"), methods=methods,
                     seeds=_seeds(raw.get("seeds")), mentors=mentors,
                     variants=_variants(raw.get("parameters"), raw.get("variants")), metrics=tuple(metrics),
                     num_cpus=float(num_cpus), description=description.strip(), shield=_shield(raw.get("shield")))


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep config file (``recipes/sweeps/*.yaml``)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise SweepConfigError(f"sweep config {str(path)!r} not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise SweepConfigError(f"sweep config {path}: not valid YAML: {e}") from e
    return parse_sweep(raw, default_name=path.stem)
