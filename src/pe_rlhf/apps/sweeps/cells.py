"""The sweep's cells: grid expansion, names, the overrides each runs with, and the bookkeeping on disk.

A cell is one run: ``method x mentor x parameter x seed``. Its name joins the parts that apply with
``__`` (``pe-rlhf__amateur__epsilon_select=0.25__s1``, ``idm-mobil__s0``); its folder is ``OUT/<name>/``.

On disk, per cell folder: ``cell.json`` (what the cell runs: written before its first attempt, compared on
every later invocation so a changed config cannot reuse a stale folder), then the recipe's outputs;
``final_eval.json`` marks the cell finished (never rerun); in a sweep with ``shield``, a trained cell is finished
when ``shielded_eval.json`` (its actor under the runtime shield, on the same scenes) is there too, and a cell that
has ``final_eval.json`` but not that gets the shielded evaluation alone, not another training.
``OUT/logs/<name>.log`` collects every attempt's output.
"""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from pe_rlhf.apps.sweeps.methods import PROXY_Q_RECIPES, MethodSpec, proxy_q_config_path
from pe_rlhf.apps.sweeps.spec import MentorSpec, SweepConfigError, SweepSpec, Variant, yaml_value

NONE = "-"  # the label of an axis that does not apply to a cell
FINAL_EVAL = "final_eval.json"
SHIELDED_EVAL = "shielded_eval.json"  # as the recipes write it (pe_rlhf.runtime.recipe.SHIELDED_EVAL)
CELL_FILE = "cell.json"
LOG_DIR = "logs"
_UNSAFE = re.compile(r"[^A-Za-z0-9._+=-]")


@dataclass(frozen=True)
class Cell:
    """One run of the sweep. ``overrides``: the recipe config overrides, in order (base, method, mentor,
    parameter, seed); ``values``: the parameter grid's ``(key, value)`` pairs (for plots)."""

    name: str
    method: MethodSpec
    mentor: str
    parameter: str
    seed: int
    overrides: tuple[str, ...]
    values: tuple = ()
    shield: float | None = None  # [s]: the trained actor is also evaluated under the runtime shield

    @property
    def row(self) -> tuple[str, str, str]:
        """The summary row the cell belongs to (seeds are aggregated)."""
        return self.method.name, self.mentor, self.parameter

    def record(self) -> dict:
        """What ``cell.json`` holds: enough to tell whether a folder was made by this cell."""
        return {"name": self.name, "recipe": self.method.recipe, "policy": self.method.policy,
                "method": self.method.name, "mentor": self.mentor, "parameter": self.parameter, "seed": self.seed,
                "overrides": list(self.overrides), "shield": self.shield}


def _safe(part: str) -> str:
    return _UNSAFE.sub("_", part)


def _mentor_overrides(method: MethodSpec, mentor: MentorSpec, index: int) -> tuple[str, ...]:
    out = [f"{method.mentor_key}={mentor.name}"]
    if mentor.kwargs and method.mentor_key != "mentor.name":
        raise SweepConfigError(f"sweep config: mentors[{index}].kwargs: method {method.name!r} sets "
                               f"{method.mentor_key}, which takes no kwargs", f"mentors[{index}].kwargs")
    out += [f"mentor.kwargs.{k}={yaml_value(v)}" for k, v in mentor.kwargs]
    return tuple(out)


def expand(spec: SweepSpec) -> list[Cell]:
    """Every cell of the grid, in order (method, mentor, parameter, seed); names unique and deterministic."""
    cells: list[Cell] = []
    for method in spec.methods:
        mentors = list(enumerate(spec.mentors)) if spec.mentors and method.mentor_key else [(None, None)]
        variants: list[Variant | None] = list(spec.variants) if spec.variants and method.parameters else [None]
        for (index, mentor), variant in ((m, v) for m in mentors for v in variants):
            for seed in spec.seeds:
                overrides = (*spec.base, *method.overrides,
                             *(_mentor_overrides(method, mentor, index) if mentor else ()),
                             *(variant.overrides if variant else ()), f"seed={seed}")  # the mentor's too
                parts = [method.name, mentor.label if mentor else None, variant.label if variant else None,
                         f"s{seed}"]
                cells.append(Cell(name="__".join(_safe(p) for p in parts if p is not None), method=method,
                                  mentor=mentor.label if mentor else NONE, parameter=variant.label if variant else NONE,
                                  seed=seed, overrides=overrides, values=variant.values if variant else (),
                                  shield=spec.shield if method.trains else None))
    names = [c.name for c in cells]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise SweepConfigError(f"sweep config: cells {duplicates} would share a folder: give the methods, mentors "
                               "or variants distinct labels")
    return cells


def check_cell_configs(cells: list[Cell]) -> None:
    """Load every cell's recipe config (validated, as the recipe will): a bad override fails here, naming
    the cell and the field, before anything runs. Cells that differ only by their seed (an integer the sweep
    config has already checked) are loaded once."""
    from pe_rlhf.runtime.config_rules import ConfigError

    checked = set()
    for cell in cells:
        key = (cell.method.recipe, cell.method.policy, tuple(o for o in cell.overrides if not o.startswith("seed=")))
        if key in checked:
            continue
        checked.add(key)
        try:
            _load_config(cell)
        except (ConfigError, ValueError) as e:
            raise SweepConfigError(f"cell {cell.name}: {e}", getattr(e, "field", None)) from e


def _load_config(cell: Cell):
    recipe = cell.method.recipe
    if recipe in (*PROXY_Q_RECIPES, "evaluate"):
        from pe_rlhf.algorithms.proxy_q.config import load_config

        cfg = load_config(proxy_q_config_path("pe_rlhf" if recipe == "evaluate" else recipe), cell.overrides)
        _build_mentor(cfg)
        if recipe == "evaluate":
            from pe_rlhf.runtime.recipe import registered_policies

            if cell.method.policy not in registered_policies():
                raise ValueError(f"policy {cell.method.policy!r} is not registered; "
                                 f"allowed: {sorted(registered_policies())}")
        return cfg
    from pe_rlhf.algorithms.baselines.config import load_baseline_config

    cfg = load_baseline_config(recipe, overrides=cell.overrides)
    if "mentor" in cfg:
        _build_mentor(cfg)
    return cfg


def _build_mentor(cfg) -> None:
    """Build a simulated mentor once: its arguments' values (``mentor.kwargs``) are checked only then."""
    from pe_rlhf.mentors.registry import MENTOR_NAMES, make_mentor

    name = str(cfg.mentor.name)
    if name in MENTOR_NAMES and name != "human":
        make_mentor(name, int(cfg.seed), **dict(cfg.mentor.kwargs or {}))


# --------------------------------------------------------------------------- bookkeeping


def cell_dir(out: Path, cell: Cell) -> Path:
    return Path(out) / cell.name


def log_path(out: Path, cell: Cell) -> Path:
    return Path(out) / LOG_DIR / f"{cell.name}.log"


def is_finished(out: Path, cell: Cell) -> bool:
    """A cell with ``final_eval.json`` (and, when it is to be shielded, ``shielded_eval.json``) is done and never
    rerun."""
    return (cell_dir(out, cell) / FINAL_EVAL).is_file() and not needs_shielded_eval(out, cell)


def needs_shielded_eval(out: Path, cell: Cell) -> bool:
    """A trained cell of a sweep with ``shield`` that has no ``shielded_eval.json`` yet."""
    return cell.shield is not None and not (cell_dir(out, cell) / SHIELDED_EVAL).is_file()


def check_folder(out: Path, cell: Cell) -> None:
    """Fail if ``OUT/<cell>`` was made by a cell with other overrides (another config under the same name),
    or holds files but no ``cell.json`` (not a sweep's folder: a rerun would empty it)."""
    path = cell_dir(out, cell) / CELL_FILE
    if not path.is_file():
        if path.parent.is_dir() and any(path.parent.iterdir()):
            raise SweepConfigError(f"{path.parent} exists but was not made by a sweep (no {CELL_FILE}); "
                                   "use another --out")
        return
    saved = json.loads(path.read_text())
    if isinstance(saved.get("overrides"), list):
        saved["overrides"] = _without_retired(saved["overrides"], saved.get("seed"))
    mine = cell.record()
    changed = [k for k in ("recipe", "policy", "overrides") if saved.get(k) != mine[k]]
    if changed:
        raise SweepConfigError(f"{path.parent} was made by another config ({', '.join(changed)} differ: "
                               f"saved {[saved.get(k) for k in changed]}, now {[mine[k] for k in changed]}); "
                               "use another --out, or delete that folder to rerun it")


def _without_retired(overrides: list, seed) -> list:
    """A ``cell.json``'s overrides without the retired ``mentor.seed=<the cell's seed>`` that cells added before the
    run's ``seed`` seeded the mentor too (issue 43): such a folder is still this cell's."""
    return [item for item in overrides if item != f"mentor.seed={seed}"]


def write_record(out: Path, cell: Cell) -> None:
    directory = cell_dir(out, cell)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / CELL_FILE).write_text(json.dumps(cell.record(), indent=2) + "\n")


def attempt_argv(directory: Path, overrides: list[str]) -> tuple[list[str], bool]:
    """The recipe's argv for the next attempt at an unfinished cell, and whether it resumes: ``--resume DIR``
    when a complete checkpoint exists, else a fresh run in an emptied folder (``cell.json`` kept)."""
    from pe_rlhf.runtime.checkpoint import find_checkpoint

    directory = Path(directory)
    if (directory / "config.yaml").is_file() and find_checkpoint(directory / "checkpoints") is not None:
        return ["--resume", str(directory)], True
    for child in directory.iterdir() if directory.is_dir() else ():
        if child.name != CELL_FILE:
            shutil.rmtree(child) if child.is_dir() else child.unlink()
    return [*overrides, "--out", str(directory)], False


def plan(out: Path, cells: list[Cell]) -> tuple[list[Cell], list[Cell]]:
    """``(finished, to_run)``; fails if a folder belongs to another config (:func:`check_folder`)."""
    for cell in cells:
        check_folder(out, cell)
    finished = [c for c in cells if is_finished(out, c)]
    return finished, [c for c in cells if not is_finished(out, c)]
