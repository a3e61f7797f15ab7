"""Hydra composition of a recipe's config: the schema, the recipe's ``config.yaml``, its profile, the overrides.

A recipe's ``config.yaml`` is a Hydra primary config (``recipes/pe_rlhf/config.yaml``)::

    defaults:
      - pe_rlhf_schema     # the structured config: every field's default (pe_rlhf.algorithms.proxy_q.config_schema)
      - _self_             # this file's values
      - profile: paper     # a config group: paper | cpu | quick | smoke (pe_rlhf.algorithms.proxy_q.config_profiles)

A :class:`RecipeSchema` names a family's structured config and its profiles: PE-RLHF, HACO and HAIM-DRL share
:data:`~pe_rlhf.algorithms.proxy_q.config_schema.PROXY_Q`; each baseline has its own (``sac_lag_schema``, ...:
:mod:`pe_rlhf.algorithms.baselines.config`). Every function here takes the schema it composes; none knows a method.
:func:`store_recipe_configs` registers a schema and its ``profile`` group in Hydra's ConfigStore, with the Hydra
settings that keep a run where it was started: no change of working directory, no ``outputs/``, ``multirun/`` or
``.hydra/`` folder, no log file (``hydra.run.dir: .``, ``hydra.sweep.dir: .``, ``hydra.output_subdir: null``,
``hydra/job_logging: none``). Every family's profiles are the one ``profile`` group (``profile=smoke`` on any
recipe's command line), so the group holds the profiles of the schema composed last; each composition registers its
own under the lock it composes under. :func:`compose_file` composes a recipe file (``@hydra.main`` composes the same
in a recipe's ``train.py``); a file without a ``defaults`` list (a partial file, a run's saved ``config.yaml``) is
composed over the schema as if it were the recipe's. Hydra's errors become a :class:`ConfigError` of one line that
names the field.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra import compose, initialize, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException
from hydra.initialize import get_gh_backup, restore_gh_from_backup
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from pe_rlhf.runtime.config_retired import check_retired_override
from pe_rlhf.runtime.config_rules import ConfigError, invalid_value
from pe_rlhf.runtime.config_schema import OPEN_GROUPS

PROFILE_GROUP = "profile"
_FILE_VALUES = "pe_rlhf_file_values"  # a file without a defaults list, over the schema
_FILE_JOB = "pe_rlhf_file_job"
# A run stays where it was started: Hydra neither changes directory nor writes outputs/, .hydra/ or a log file.
HYDRA_SETTINGS = {"run": {"dir": "."}, "sweep": {"dir": ".", "subdir": "."}, "output_subdir": None,
                  "job": {"chdir": False},
                  "help": {"footer": "Recipe flags: --out DIR (the run folder; default runs/<method>-<time>), "
                                     "--compare POLICY (also evaluate e.g. idm-mobil on the same test scenes), "
                                     "--shield [SECONDS] (also evaluate the trained actor under the runtime shield), "
                                     "--resume DIR [key=value ...] (continue the run in DIR).\n"
                                     "Powered by Hydra (https://hydra.cc); --hydra-help for Hydra's own flags."}}
HYDRA_DEFAULTS_LIST = [{"override hydra/job_logging": "none"}, {"override hydra/hydra_logging": "none"},
                       "_self_"]
_LOCK = threading.RLock()  # Hydra's compose state and the file's ConfigStore entries are globals


@dataclass(frozen=True, eq=False)
class RecipeSchema:
    """A recipe family's structured config as Hydra composes it: ``name`` in the ConfigStore, ``defaults`` (the
    schema's values as a new plain dict each call), ``profiles`` (``{profile: values}``, the ``profile`` group),
    ``open_groups`` (free-form groups, checked by name after composition) and ``variant_groups`` (groups whose
    settings depend on one of their fields, e.g. the loss's on ``loss.objective``: empty and open in Hydra's node,
    so that the recipe file brings its variant's settings and nothing else; the family completes and checks them
    after composition)."""

    name: str
    defaults: Callable[[], dict[str, Any]]
    profiles: Mapping[str, Mapping[str, Any]]
    open_groups: tuple[str, ...] = OPEN_GROUPS
    variant_groups: tuple[str, ...] = ()

    def node_values(self) -> dict[str, Any]:
        """The defaults Hydra composes over: :attr:`defaults` with each variant group empty."""
        values = self.defaults()
        values.update({group: {} for group in self.variant_groups})
        return values


_STORED: set[str] = set()  # the schemas registered in this process (they are constants)
_PROFILES_OF: str | None = None  # the schema whose profiles the profile group holds


def schema_node(schema: RecipeSchema) -> DictConfig:
    """The schema's defaults as a DictConfig: closed groups (an unknown key fails) but its open groups; not
    typed (the rules check every value after composition)."""
    cfg = OmegaConf.create(schema.node_values())
    _close(cfg, schema)
    return cfg


def store_recipe_configs(schema: RecipeSchema) -> None:
    """Register ``schema`` (once a process, with :data:`HYDRA_SETTINGS`) and its profiles as the ``profile``
    group (in place of another family's)."""
    global _PROFILES_OF
    with _LOCK:
        store = ConfigStore.instance()
        if schema.name not in _STORED:
            _STORED.add(schema.name)
            node = OmegaConf.create({"defaults": HYDRA_DEFAULTS_LIST, "hydra": HYDRA_SETTINGS, **schema.node_values()})
            _close(node, schema)
            store.store(name=schema.name, node=node)
        if _PROFILES_OF != schema.name:
            store.repo.pop(PROFILE_GROUP, None)  # another family's: a profile it has and this one lacks goes too
            for name, values in schema.profiles.items():
                store.store(group=PROFILE_GROUP, name=name, node={**values, "profile": name}, package="_global_")
            _PROFILES_OF = schema.name


def _close(cfg: DictConfig, schema: RecipeSchema) -> None:
    OmegaConf.set_struct(cfg, True)
    for group in (*schema.open_groups, *schema.variant_groups):
        node = OmegaConf.select(cfg, group)
        if node is not None:
            OmegaConf.set_struct(node, False)


def override_key(item: str) -> str:
    """The dotted key of a Hydra override (``+a.b=1``, ``~a.b``, ``a.b=1`` -> ``a.b``)."""
    return item.split("=", 1)[0].strip().lstrip("+~")


# YAML's special floats, which overrides took before Hydra (whose grammar spells them nan, inf, -inf).
YAML_FLOATS = {".nan": "nan", ".inf": "inf", "+.inf": "inf", "-.inf": "-inf"}


def check_overrides(overrides: Iterable[str], profiles: Mapping[str, Any]) -> list[str]:
    """The overrides as a list, each ``key=value`` (Hydra's ``+key=value`` and ``~key`` too), a YAML special float
    (``.nan``, ``.inf``, ``-.inf``) spelled as Hydra reads it; a profile not in ``profiles`` fails here, naming
    them."""
    if isinstance(overrides, str):  # a lone "a=b" would otherwise be iterated character by character
        overrides = [overrides]
    items = [_hydra_float(item) for item in overrides]
    for item in items:
        deletion = isinstance(item, str) and item.startswith("~")
        if not isinstance(item, str) or not override_key(item) or ("=" not in item and not deletion):
            raise ConfigError(f"override {item!r} is not of the form key=value (e.g. optim.lr=3e-4)")
        if "=" in item:
            check_retired_override(override_key(item), item.split("=", 1)[1])
        if override_key(item) == PROFILE_GROUP and "=" in item:
            profile = item.split("=", 1)[1].strip()
            if profile not in profiles:
                raise invalid_value(PROFILE_GROUP, profile, f"allowed: {list(profiles)}")
    return items


def _hydra_float(item: Any) -> Any:
    if isinstance(item, str) and "=" in item:
        key, value = item.split("=", 1)
        spelled = YAML_FLOATS.get(value.strip().lower())
        if spelled is not None:
            return f"{key}={spelled}"
    return item


def compose_file(path: Path, overrides: list[str], values: Mapping[str, Any], *, recipe: bool,
                 apply_profile: bool = True, schema: RecipeSchema) -> DictConfig:
    """Compose the config file ``path`` whose values (its ``defaults`` list aside) are ``values``: with ``recipe``,
    a Hydra primary config (schema, file, profile from its ``defaults`` list); else ``values`` over ``schema``,
    then its profile (``profile:`` in ``values``; none with ``apply_profile=False``: a run's saved config). Then
    ``overrides``. An unknown key in the file fails naming it, before Hydra. Raises :class:`ConfigError`."""
    if recipe:
        base = schema_node(schema)
        for key in leaf_keys(values):
            check_key(base, key, f"config file {path}")
        return _compose(path.resolve().parent, path.stem, overrides, schema)
    profile = next((i.split("=", 1)[1].strip() for i in reversed(overrides) if override_key(i) == PROFILE_GROUP),
                   values.get(PROFILE_GROUP, schema.defaults()[PROFILE_GROUP]))
    if profile not in schema.profiles:
        raise invalid_value(PROFILE_GROUP, profile, f"allowed: {list(schema.profiles)}")
    base = schema_node(schema)
    merge_values(base, values, f"config file {path}")
    entries: list[Any] = [_FILE_VALUES, "_self_"] + ([{PROFILE_GROUP: profile}] if apply_profile else [])
    with _LOCK:  # the file's entries stay this call's until it has composed
        ConfigStore.instance().store(name=_FILE_VALUES, node=base)
        ConfigStore.instance().store(name=_FILE_JOB, node={"defaults": entries})
        cfg = _compose(None, _FILE_JOB, [i for i in overrides if override_key(i) != PROFILE_GROUP], schema)
    cfg.profile = profile
    return cfg


def _compose(config_dir: Path | None, name: str, overrides: list[str], schema: RecipeSchema) -> DictConfig:
    with _LOCK:
        store_recipe_configs(schema)
        backup = get_gh_backup()  # inside @hydra.main (a run loading another run's config) Hydra is initialized
        GlobalHydra.instance().clear()
        try:
            start = (initialize_config_dir(str(config_dir), version_base=None) if config_dir is not None
                     else initialize(version_base=None, config_path=None))
            with start:
                try:
                    return compose(config_name=name, overrides=overrides)
                except (HydraException, OmegaConfBaseException) as e:
                    raise _explain(e, config_dir, name, overrides) from e
        finally:
            restore_gh_from_backup(backup)


def _explain(error: Exception, config_dir: Path | None, name: str, overrides: list[str]) -> ConfigError:
    """One line naming the field: an unknown key as :func:`check_key` says it, else Hydra's own words."""
    values = [i for i in overrides if override_key(i) != PROFILE_GROUP and not i.startswith("+")]
    try:
        base = compose(config_name=name, overrides=[i for i in overrides if i not in values])
    except (HydraException, OmegaConfBaseException):
        base = None
    if base is not None:
        for item in values:
            check_key(base, override_key(item), "command-line override")
    cause = error.__cause__ or error
    detail = " ".join(str(cause).split())
    where = f" ({config_dir / name}.yaml)" if config_dir is not None else ""
    return ConfigError(f"cannot compose the config{where}: {detail}")


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
    """Merge ``values`` into ``cfg`` in place, every key checked first (:func:`check_key`)."""
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


__all__ = ["HYDRA_SETTINGS", "PROFILE_GROUP", "RecipeSchema", "check_key", "check_overrides", "compose_file",
           "leaf_keys", "merge_values", "override_key", "schema_node", "store_recipe_configs"]
