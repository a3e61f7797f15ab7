"""The rows of a comparison: which finished run folders (one per seed) or evaluation JSONs each holds, and
its label.

A row is either *trained* (run folders: ``final_eval.json`` required, ``config.yaml`` and ``metrics.csv``
read when present) or *evaluation-only* (``pe-rlhf evaluate --json`` files: test metrics, no training).
Sources:

- ``LABEL=DIR[,DIR...]`` (``--row``): each DIR a run folder, or a folder of run folders (its finished
  subfolders, e.g. ``runs/haco_lanes`` for ``seed_0``, ``seed_1``); ``LABEL=`` may be left out, then the
  label is inferred from the runs' ``config.yaml``.
- ``LABEL=FILE.json[,FILE.json...]`` (``--eval``); without ``LABEL=`` the JSON's ``policy`` names it.
- a glob pattern (``--glob``): matched run folders, folders of run folders and evaluation JSONs, grouped
  into rows by their folder (``runs/lanes/seed_*`` -> one row; a sweep's cells ``NAME__sSEED`` -> one row
  per NAME) and labelled by inference.

Inferred labels that come out equal get the folder's (or file's) name appended (``PE-RLHF (lanes)``,
``PE-RLHF (lanes_eps0b)``); labels given twice are an error.

Label inference (:func:`infer_label`): an evaluation's ``policy`` (``idm-mobil`` -> ``IDM-MOBIL``; a
sweep's evaluation-only cell is an evaluation row too); else the method the run recorded by its registry name
(``"algorithm"`` in ``final_eval.json``, ``algorithm:`` in ``config.yaml``), shown by its
:data:`~pe_rlhf.algorithms.ALGORITHMS` display name (``PE-RLHF``, ``SAC-RS``, ...; a PE-RLHF run with the
disturbance critic is ``PE-RLHF+disturbance``). Run folders from before that record: a baseline's
``final_eval.json`` / ``config.yaml`` ``method`` (``SAC-RS``, ``BC``, ...); else the proxy-Q recipe's physics /
disturbance switches and its loss (:func:`pe_rlhf.algorithms.proxy_q.config.method_name`: PE-RLHF, HACO, HAIM-DRL, PVP). A
mentor other than the professional is appended (``PE-RLHF (amateur)``).
"""

from __future__ import annotations

import glob as globlib
import json
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

FINAL_EVAL, CONFIG, METRICS_CSV = "final_eval.json", "config.yaml", "metrics.csv"
TRAINED, EVALUATION = "trained", "evaluation"
# the paper's Table 1 order (spec section 7, plus the baselines it leaves out); other labels come after
PAPER_ORDER = ("IDM-MOBIL", "SAC-RS", "SAC-Lag", "PPO-RS", "PPO-Lag", "CPO", "CQL", "BC", "GAIL", "HG-DAgger",
               "IWR", "HACO", "HAIM-DRL", "PE-RLHF")
_SEED_DIR = re.compile(r"^(seed|s)[_-]?\d+$")
_SWEEP_CELL = re.compile(r"^(.+)__s\d+$")  # pe_rlhf.apps.sweeps.cells names: METHOD[__MENTOR][__PARAMETER]__sSEED


class CompareError(ValueError):
    """A bad row, path or file; the message names it."""


@dataclass
class Source:
    """One seed of a row: a run folder (``final`` from its ``final_eval.json``) or an evaluation JSON."""

    path: Path
    final: dict[str, Any]
    config: dict[str, Any] = field(default_factory=dict)

    @property
    def metrics_csv(self) -> Path | None:
        path = self.path / METRICS_CSV
        return path if self.path.is_dir() and path.is_file() else None


@dataclass
class Row:
    """A table row: its label, kind (:data:`TRAINED` / :data:`EVALUATION`) and one source per seed."""

    label: str
    kind: str
    sources: list[Source]
    group: Path | None = None  # where an inferred label's row came from (to tell equal labels apart)


def _load_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except OSError as e:
        raise CompareError(f"{path}: cannot read ({e.strerror or e})") from e
    except json.JSONDecodeError as e:
        raise CompareError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(data, dict):
        raise CompareError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def _load_config(directory: Path) -> dict[str, Any]:
    path = directory / CONFIG
    if not path.is_file():
        return {}
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        data = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except (OSError, OmegaConfBaseException, ValueError) as e:
        raise CompareError(f"{path}: not a readable YAML config ({e})") from e
    return data if isinstance(data, dict) else {}


def load_run(directory: str | Path) -> Source:
    """A finished run folder; CompareError naming the path when it is missing, unfinished or unreadable."""
    directory = Path(directory)
    if not directory.is_dir():
        raise CompareError(f"{directory}: no such run folder")
    if not (directory / FINAL_EVAL).is_file():
        raise CompareError(f"{directory}: no {FINAL_EVAL} (not a finished run folder)")
    return Source(directory, _load_json(directory / FINAL_EVAL), _load_config(directory))


def load_evaluation(path: str | Path) -> Source:
    """A ``pe-rlhf evaluate --json`` file (or any ``final_eval.json``) as an evaluation-only seed."""
    path = Path(path)
    if not path.is_file():
        raise CompareError(f"{path}: no such evaluation JSON")
    final = _load_json(path)
    if not isinstance(final.get("success_rate"), dict) or "mean" not in final["success_rate"]:
        raise CompareError(f"{path}: not an evaluation summary (no success_rate mean; write one with "
                           "`pe-rlhf evaluate --json FILE`)")
    return Source(path, final)


def finished_runs(directory: Path) -> tuple[list[Path], list[Path]]:
    """``(finished, unfinished)`` run subfolders of ``directory`` (those with / without ``final_eval.json``
    among the ones holding a ``config.yaml`` or ``metrics.csv``), in natural order."""
    def natural(p: Path):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]

    subdirs = sorted((p for p in directory.iterdir() if p.is_dir()), key=natural)
    finished = [p for p in subdirs if (p / FINAL_EVAL).is_file()]
    unfinished = [p for p in subdirs if p not in finished and ((p / CONFIG).is_file() or (p / METRICS_CSV).is_file())]
    return finished, unfinished


def expand_run_dir(directory: str | Path, notes: list[str]) -> list[Path]:
    """``directory`` itself when it is a finished run, else its finished run subfolders (unfinished ones are
    noted); CompareError naming the path when it has neither."""
    directory = Path(directory)
    if (directory / FINAL_EVAL).is_file() or not directory.is_dir():
        return [directory]  # load_run names what is wrong
    finished, unfinished = finished_runs(directory)
    notes.extend(f"skipped unfinished run {p} (no {FINAL_EVAL})" for p in unfinished)
    if not finished:
        raise CompareError(f"{directory}: no {FINAL_EVAL} here nor in its subfolders (not a finished run folder)")
    return finished


def _get(config: dict, dotted: str, default: Any = None) -> Any:
    node: Any = config
    for key in dotted.split("."):
        if not isinstance(node, dict) or key not in node:
            return default
        node = node[key]
    return node


def infer_label(source: Source) -> str:
    """The method name of a run folder or evaluation JSON (see the module docstring)."""
    final, config = source.final, source.config
    if not source.path.is_dir() or final.get("policy"):  # an evaluation JSON, or a sweep's evaluation cell
        policy = final.get("policy")
        if not policy:
            return source.path.stem
        policy = str(policy)
        return "IDM-MOBIL" + policy[len("idm-mobil"):] if policy.startswith("idm-mobil") else policy
    mentor = _get(config, "mentor.name")
    algorithm = final.get("algorithm") or config.get("algorithm")
    if algorithm:
        name = _recorded_label(str(algorithm), config)
        mentor = mentor or _get(config, "data.mentor")
    elif final.get("method") or config.get("method"):
        name = final.get("method")
        if not name:
            from pe_rlhf.algorithms import ALGORITHMS

            key = str(config["method"])  # a baseline's recipe name, e.g. sac_rs
            entry = ALGORITHMS.get(key.replace("_", "-"))
            name = entry.display if entry else key
        mentor = mentor or _get(config, "data.mentor")
    elif "physics" in config or "selector" in config:
        from omegaconf import OmegaConf

        from pe_rlhf.runtime.config_rules import ConfigError
        from pe_rlhf.algorithms.proxy_q.config import method_name

        switches = OmegaConf.create({**{group: {"enabled": bool(_get(config, f"{group}.enabled", False))}
                                        for group in ("physics", "disturbance")},
                                     "loss": {"objective": str(_get(config, "loss.objective", "paper"))}})
        try:
            name = method_name(switches)
        except ConfigError as e:
            raise CompareError(f"{source.path / CONFIG}: {e}; give the row a LABEL=") from e
    else:
        raise CompareError(f"{source.path}: cannot tell the method (no {CONFIG} with a method or physics/selector "
                           "groups); give the row a LABEL=")
    return name if mentor in (None, "professional") else f"{name} ({mentor})"


def _recorded_label(algorithm: str, config: dict) -> str:
    """The display name of a registry name a run recorded (an unknown one as it is)."""
    from pe_rlhf.algorithms import ALGORITHMS

    entry = ALGORITHMS.get(algorithm)
    if entry is None:
        return algorithm
    variant = algorithm == "pe-rlhf" and bool(_get(config, "disturbance.enabled", False))
    return entry.display + ("+disturbance" if variant else "")


def _split_spec(spec: str) -> tuple[str | None, list[str]]:
    """``"LABEL=A,B"`` -> ``("LABEL", ["A", "B"])``; ``"A,B"`` -> ``(None, [...])``."""
    label, sep, rest = spec.partition("=")
    if not sep or Path(spec).exists():
        label, rest = None, spec
    paths = [p.strip() for p in rest.split(",") if p.strip()]
    if not paths:
        raise CompareError(f"{spec!r}: expected LABEL=PATH[,PATH...]")
    return (label.strip() or None) if label is not None else None, paths


def _label_of(sources: list[Source], given: str | None) -> str:
    if given:
        return given
    labels = {s.path: infer_label(s) for s in sources}
    if len(set(labels.values())) > 1:
        described = ", ".join(f"{p} ({lab})" for p, lab in labels.items())
        raise CompareError(f"one row holds different methods: {described}; give it a LABEL=")
    return next(iter(labels.values()))


def _unique(paths: list[Path]) -> list[Path]:
    seen, unique = set(), []
    for path in paths:
        if path.resolve() not in seen:
            seen.add(path.resolve())
            unique.append(path)
    return unique


def _group_of(run: Path) -> Path:
    """What names a run's row: the parent of a ``seed_N`` / ``sN`` folder; a sweep cell ``NAME__sN`` without
    its seed (``OUT/NAME``); else the folder itself."""
    if _SEED_DIR.match(run.name):
        return run.parent
    cell = _SWEEP_CELL.match(run.name)
    return run.parent / cell.group(1) if cell else run


def _kind(sources: list[Source]) -> str:
    """A sweep's evaluation-only cells (``final_eval.json`` with a ``policy``) are evaluation rows."""
    return EVALUATION if all(s.final.get("policy") for s in sources) else TRAINED


def run_row(spec: str, notes: list[str]) -> Row:
    """A ``--row LABEL=DIR[,DIR...]`` row."""
    label, dirs = _split_spec(spec)
    paths = _unique([run for d in dirs for run in expand_run_dir(d, notes)])
    sources = [load_run(p) for p in paths]
    groups = {_group_of(p) for p in paths}  # an inferred label that clashes gets the folder's name
    group = groups.pop() if label is None and len(groups) == 1 else None
    return Row(_label_of(sources, label), _kind(sources), sources, group=group)


def evaluation_row(spec: str) -> Row:
    """A ``--eval LABEL=FILE.json[,FILE.json...]`` row."""
    label, files = _split_spec(spec)
    sources = [load_evaluation(p) for p in _unique([Path(f) for f in files])]
    group = sources[0].path if label is None and len(sources) == 1 else None
    return Row(_label_of(sources, label), EVALUATION, sources, group=group)


def glob_rows(pattern: str, notes: list[str]) -> list[Row]:
    """The rows a ``--glob`` pattern's matches make (see the module docstring)."""
    matches = sorted(globlib.glob(pattern, recursive=True))
    if not matches:
        raise CompareError(f"--glob {pattern!r} matched nothing")
    runs: list[Path] = []
    rows: list[Row] = []
    for match in map(Path, matches):
        if match.is_file() and match.name == FINAL_EVAL:
            runs.append(match.parent)
        elif match.is_file() and match.suffix == ".json":
            source = load_evaluation(match)
            rows.append(Row(infer_label(source), EVALUATION, [source], group=match))
        elif match.is_dir() and (match / FINAL_EVAL).is_file():
            runs.append(match)
        elif match.is_dir():
            finished, unfinished = finished_runs(match)
            runs.extend(finished)
            notes.extend(f"skipped unfinished run {p} (no {FINAL_EVAL})" for p in unfinished)
            if not finished and not unfinished:
                unfinished_run = (match / CONFIG).is_file() or (match / METRICS_CSV).is_file()
                notes.append(f"skipped unfinished run {match} (no {FINAL_EVAL})" if unfinished_run
                             else f"skipped {match}: no {FINAL_EVAL} here nor in its subfolders")
    groups: dict[tuple[Path, str], list[Source]] = {}
    for path in _unique(runs):
        source = load_run(path)
        groups.setdefault((_group_of(path), infer_label(source)), []).append(source)
    rows += [Row(label, _kind(sources), sources, group=group) for (group, label), sources in groups.items()]
    if not rows:
        raise CompareError(f"--glob {pattern!r}: no finished run folder or evaluation JSON among its matches")
    return rows


def disambiguate(rows: list[Row]) -> None:
    """Equal labels: inferred ones (--glob, --row without LABEL=) get their folder's name appended (its path
    if the names are equal too); equal labels left after that (given ones) are an error."""
    def clashing() -> list[Row]:
        counts = Counter(r.label for r in rows)
        return [r for r in rows if counts[r.label] > 1]

    base = {id(r): r.label for r in rows}
    for describe in (lambda g: g.stem if g.is_file() else g.name, str):
        for row in clashing():
            if row.group is not None:
                row.label = f"{base[id(row)]} ({describe(row.group)})"
    twice = sorted({r.label for r in clashing()})
    if twice:
        raise CompareError(f"row label(s) given twice: {', '.join(twice)}")


def order_rows(rows: list[Row], order: list[str] | None = None) -> list[Row]:
    """``order`` (labels) first in that order, the rest after; without it, the paper's Table 1 order
    (:data:`PAPER_ORDER`, by the method name a label starts with), other labels after; ties keep the order
    given."""
    if order:
        labels = [r.label for r in rows]
        unknown = [label for label in order if label not in labels]
        if unknown:
            raise CompareError(f"--order: no row labelled {', '.join(map(repr, unknown))}; rows: {', '.join(labels)}")
        rank = {label: i for i, label in enumerate(order)}
        return sorted(rows, key=lambda r: rank.get(r.label, len(rank)))

    def paper_rank(row: Row) -> tuple[int, int]:  # by the longest paper method the label starts with (IDM-MOBIL-stop)
        ranks = [(len(name), i) for i, name in enumerate(PAPER_ORDER) if row.label.startswith(name)]
        if not ranks:
            return len(PAPER_ORDER), 1
        length, rank = max(ranks)
        rest = row.label[length:]
        return rank, 0 if not rest or rest.startswith(" (") else 1  # the method itself before its variants
    return sorted(rows, key=paper_rank)


def collect_rows(runs: list[str] = (), evaluations: list[str] = (), globs: list[str] = (),
                 order: list[str] | None = None) -> tuple[list[Row], list[str]]:
    """Every row of ``--row`` / ``--eval`` / ``--glob`` specs, labelled and ordered; and notes (skipped
    unfinished runs). CompareError naming the bad path or spec."""
    notes: list[str] = []
    rows = [run_row(s, notes) for s in runs] + [evaluation_row(s) for s in evaluations]
    for pattern in globs:
        rows += glob_rows(pattern, notes)
    if not rows:
        raise CompareError("no rows: give --row LABEL=DIR, --eval LABEL=FILE.json or --glob PATTERN")
    disambiguate(rows)
    return order_rows(rows, order), notes
