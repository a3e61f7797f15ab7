"""Claims over seeds: mean and a 95% bootstrap confidence interval per method and mentor, from a sweep's cells.

``claims_summary(cells_csv)`` reads a sweep folder's ``cells.csv`` (:mod:`pe_rlhf.apps.sweeps.summary`) and returns
``{claim: {method: {"success": [mean, lo, hi], "test_safety": [...], "train_violations": [...],
"takeover_usage": [...], "seeds": N, "per_seed": {"seed": [...], "success": [...], "test_safety": [...]}}}}``,
a claim being the mentor's label (``professional``,
``adversarial``) and a method the sweep's name with ``-`` as ``_`` (``pe_rlhf``, ``haco``, ``idm_mobil``).
An evaluation-only method (IDM-MOBIL: mentor ``-`` in the cells) joins every claim. ``test_safety`` is
``1 - test safety violation rate``. The interval is :func:`pe_rlhf.evaluation.statistics.bootstrap_interval`
(a 95% bootstrap CI of the mean over seeds); with one seed, or when every seed agrees, ``lo == hi == mean``.
A metric a method does not have (IDM-MOBIL is not trained) is ``null``. Only finished cells count.

Where a claim's cells were also evaluated under the runtime shield (a sweep with ``shield``: the ``cells.csv`` columns
``shielded_success_rate``, ``shielded_safety_violation``, ``override_share``), every method of that claim gains
``"shielded_success"``, ``"shielded_test_safety"`` and ``"override_share"`` as ``[mean, lo, hi]`` (``null`` for a
method without them, e.g. IDM-MOBIL) and its ``per_seed`` the lists ``shielded_success`` and
``shielded_test_safety``; ``summary.md`` shows a ``<method> shielded`` row under the method's, README's table a
shielded-success column.

Where the cells carry a ``train_violations_after`` column (:func:`add_violations_after`: the training safety
violations logged after a given env step, e.g. after a collapsing mentor's switch or after the warm-up), every
method of that claim gains ``"train_violations_after": [mean, lo, hi]`` (``null`` for a method without it).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from pe_rlhf.apps.sweeps.summary import read_cells_csv
from pe_rlhf.evaluation.statistics import bootstrap_interval  # re-exported: older callers import it here

COLUMNS = {"success": ("success_rate", False), "test_safety": ("safety_violation", True),
           "train_violations": ("train_safety_violations", False), "takeover_usage": ("takeover_data_usage", False)}
OPTIONAL_COLUMNS = {"train_violations_after": ("train_violations_after", False),
                    "shielded_success": ("shielded_success_rate", False),
                    "shielded_test_safety": ("shielded_safety_violation", True),
                    "override_share": ("override_share", False)}
SHIELDED_PER_SEED = {"shielded_success": ("shielded_success_rate", False),
                     "shielded_test_safety": ("shielded_safety_violation", True)}
NO_MENTOR = "-"  # the mentor column of an evaluation-only cell
VIOLATIONS = "train/safety_violations_total"  # cumulative, in each run's metrics.csv
MISSING = (None, "", "nan")  # a cells.csv value that holds no number


def violations_after(run_dir: str | Path, step: int) -> float:
    """The training safety violations a run logged after env step ``step``: the cumulative count in the last row
    of its ``metrics.csv`` less the count in the last row at or before ``step`` (0 when no row is that early).
    NaN when the run logged no violation count."""
    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    path = Path(run_dir) / "metrics.csv"
    if not path.is_file():
        return math.nan
    _, rows = read_metrics_csv(path)
    rows = [r for r in rows if VIOLATIONS in r and "env_steps" in r]
    if not rows:
        return math.nan
    before = [r[VIOLATIONS] for r in rows if r["env_steps"] <= step]
    return rows[-1][VIOLATIONS] - (before[-1] if before else 0.0)


def add_violations_after(sweep_dir: str | Path, step: int, out_csv: str | Path) -> list[dict]:
    """A copy of ``sweep_dir/cells.csv`` at ``out_csv`` with a ``train_violations_after`` column: each cell's
    :func:`violations_after` ``step``, read from ``sweep_dir/<cell>/metrics.csv`` (NaN for evaluation-only cells).
    Returns the rows written."""
    sweep_dir = Path(sweep_dir)
    source = sweep_dir / "cells.csv"
    if not source.is_file():
        raise FileNotFoundError(f"{source}: no such cells.csv")
    with open(source, newline="") as f:
        reader = csv.DictReader(f)
        fields = [c for c in reader.fieldnames or [] if c != "train_violations_after"] + ["train_violations_after"]
        rows = list(reader)
    for r in rows:
        r["train_violations_after"] = violations_after(sweep_dir / r["cell"], step)
    with open(out_csv, "w", newline="") as f:
        writer = csv.DictWriter(f, fields)
        writer.writeheader()
        writer.writerows(rows)
    return rows


def read_cells(sources: str | Path | list[str | Path]) -> list[dict]:
    """The finished rows of one or more ``cells.csv``; a source ``PATH:METHOD,METHOD`` keeps only those methods
    (:func:`~pe_rlhf.apps.sweeps.summary.read_cells_csv`), so that the claims can take each method from the sweep
    that ran its final configuration."""
    return [r for r in read_cells_csv(sources) if r.get("status") == "finished"]


def claims_summary(cells_csv: str | Path | list[str | Path]) -> dict:
    """The summary (module docstring) of the finished cells in ``cells_csv`` (one or more sources, see
    :func:`read_cells`)."""
    rows = read_cells(cells_csv)
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["mentor"], r["method"].replace("-", "_")), []).append(r)
    claims = sorted({mentor for mentor, _ in groups if mentor != NO_MENTOR})
    for (mentor, method), members in list(groups.items()):
        if mentor == NO_MENTOR:  # evaluation-only: the same numbers stand beside every claim
            del groups[(mentor, method)]
            for claim in claims:
                groups.setdefault((claim, method), members)
    optional: dict[str, dict] = {}  # per claim: the optional columns any of its cells fills
    for (mentor, _), members in groups.items():
        for name, spec in OPTIONAL_COLUMNS.items():
            if any(r.get(spec[0]) not in MISSING for r in members):
                optional.setdefault(mentor, {})[name] = spec
    out: dict = {}
    for (mentor, method), members in sorted(groups.items()):
        entry = {}
        for name, (column, complement) in dict(COLUMNS, **optional.get(mentor, {})).items():
            values = [float(r[column]) if r.get(column) not in MISSING else math.nan for r in members]
            if complement:
                values = [1.0 - v for v in values]
            entry[name] = bootstrap_interval(values)
        entry["seeds"] = len(members)
        entry["per_seed"] = per_seed(members)
        out.setdefault(mentor, {})[method] = entry
    return out


def per_seed(members: list[dict]) -> dict[str, list]:
    """``{"seed": [...], "success": [...], "test_safety": [...]}`` of one method's finished cells, in seed order (NaN
    where a cell has no value)."""
    ordered = sorted(members, key=lambda r: int(float(r["seed"])))

    def column(name: str, complement: bool) -> list[float]:
        values = [float(r[name]) if r.get(name) not in MISSING else math.nan for r in ordered]
        return [1.0 - v if complement else v for v in values]

    out = {"seed": [int(float(r["seed"])) for r in ordered], "success": column("success_rate", False),
           "test_safety": column("safety_violation", True)}
    if any(r.get("shielded_success_rate") not in MISSING for r in ordered):  # evaluated under the shield too
        out.update({name: column(*spec) for name, spec in SHIELDED_PER_SEED.items()})
    return out


def markdown_table(summary: dict) -> str:
    """One row per claim and method: each metric as ``mean [lo, hi]``."""
    lines = ["| claim | method | seeds | test success | test safety | training violations | takeover usage |",
             "|---|---|---|---|---|---|---|"]

    def cell(v, fmt=".2f"):
        return "—" if v is None else f"{v[0]:{fmt}} [{v[1]:{fmt}}, {v[2]:{fmt}}]"

    for claim, methods in summary.items():
        for method, m in methods.items():
            lines.append(f"| {claim} | {method} | {m['seeds']} | {cell(m['success'])} | {cell(m['test_safety'])} | "
                         f"{cell(m['train_violations'], '.1f')} | {cell(m['takeover_usage'])} |")
            if is_shielded(m):
                lines.append(f"| {claim} | {method} shielded (override share {cell(m['override_share'], '.3f')}) | "
                             f"{m['seeds']} | {cell(m['shielded_success'])} | {cell(m['shielded_test_safety'])} | "
                             "— | — |")
    return "\n".join(lines)


def is_shielded(entry: dict) -> bool:
    """Whether a method's summary entry has its cells' evaluation under the runtime shield."""
    value = entry.get("shielded_success")
    return value is not None and all(isinstance(x, (int, float)) and math.isfinite(x) for x in value)


def write_claims(cells_csv: str | Path | list[str | Path], out_dir: str | Path) -> dict:
    """``summary.json`` and ``summary.md`` in ``out_dir``; returns the summary."""
    summary = claims_summary(cells_csv)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out_dir / "summary.md").write_text(markdown_table(summary) + "\n")
    return summary


# README's results table (:func:`readme_table`): readable method names, the mentors and methods in reading order
# (others follow as the summary gives them, under their own names).
METHOD_LABELS = {"pe_rlhf": "PE-RLHF", "pe_rlhf_paper_loss": "PE-RLHF (paper's loss)", "pvp": "PVP", "haco": "HACO",
                 "idm_mobil": "IDM-MOBIL"}
MENTOR_ORDER = ("professional", "adversarial", "amateur", "collapsing")
README_TABLE_START = "<!-- claims-table: start (benchmarks/claims_summary.py --readme writes it) -->"
README_TABLE_END = "<!-- claims-table: end -->"


def _in_order(names, preferred: tuple[str, ...]) -> list[str]:
    return [n for n in preferred if n in names] + [n for n in names if n not in preferred]


def _interval(v, fmt: str) -> str:
    """``mean [lo, hi]``; the mean alone where every seed agrees (one seed, a deterministic policy); ``—`` for none."""
    if v is None or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
        return "—"
    mean, lo, hi = (f"{x:{fmt}}" for x in v)
    return mean if v[0] == v[1] == v[2] else f"{mean} [{lo}, {hi}]"


def readme_table(summary: dict, steps: int = 30_000, warmup: int = 10_000,
                 scenes: str = "all 50 test scenes (1000–1049)") -> str:
    """README's results table from a claims ``summary`` (module docstring): one row per mentor and method, methods by
    their readable name (:data:`METHOD_LABELS`), each metric ``mean [lo, hi]``, then a line saying what a cell is
    (``steps`` env steps, ``warmup`` of them the mentor's warm-up, the final evaluation on ``scenes``). A method
    without training metrics (IDM-MOBIL) is evaluated only, with no mentor: its seeds show as ``—`` and its row
    stands once, under the first mentor that has it. Where the agents were also evaluated under the runtime shield,
    their shielded success is a column and the line gives the lowest shielded test safety of any row."""
    shielded = [m for ms in summary.values() for m in ms.values() if is_shielded(m)]
    columns = (["mentor", "method", "seeds", "test success", "test safety"] + ["shielded success"] * bool(shielded)
               + ["training violations", "takeover data usage"])
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    evaluated_only_shown: set[str] = set()
    for mentor in _in_order(list(summary), MENTOR_ORDER):
        methods = summary[mentor]
        for method in _in_order(list(methods), tuple(METHOD_LABELS)):
            m = methods[method]
            trained = m.get("train_violations") is not None
            if not trained:  # evaluated only, with no mentor: the same row under every mentor, shown once
                if method in evaluated_only_shown:
                    continue
                evaluated_only_shown.add(method)
            shield_cell = (f" {_interval(m['shielded_success'], '.2f') if is_shielded(m) else '—'} |"
                           if shielded else "")
            lines.append(f"| {mentor} | {METHOD_LABELS.get(method, method)} | {m['seeds'] if trained else '—'} | "
                         f"{_interval(m.get('success'), '.2f')} | {_interval(m.get('test_safety'), '.2f')} |"
                         f"{shield_cell} {_interval(m.get('train_violations'), '.1f')} | "
                         f"{_interval(m.get('takeover_usage'), '.2f')} |")
    note = (f"Mean [95% bootstrap interval] over seeds; each learned cell {steps // 1000}K env steps "
            f"({warmup // 1000}K of them the mentor's warm-up), final evaluation on {scenes}; "
            "test safety is 1 - the episodes' safety violation rate; IDM-MOBIL is evaluated, not trained, and needs "
            "no mentor")
    if shielded:
        note += "; shielded success is the same agents deployed under the runtime shield (docs/guide/shield.md)"
        safeties = [m["shielded_test_safety"][0] for m in shielded if m.get("shielded_test_safety")
                    and math.isfinite(m["shielded_test_safety"][0])]
        if safeties:
            note += f", whose test safety is {min(safeties):.2f} or above in every row"
    return "\n".join(lines + ["", note + "."])


def with_readme_table(text: str, table: str) -> str:
    """``text`` (README.md) with what lies between :data:`README_TABLE_START` and :data:`README_TABLE_END` replaced
    by ``table``. ``ValueError`` when the markers are not there once each, in order."""
    start, end = text.find(README_TABLE_START), text.find(README_TABLE_END)
    if text.count(README_TABLE_START) != 1 or text.count(README_TABLE_END) != 1 or end < start:
        raise ValueError(f"README: needs the lines {README_TABLE_START!r} and {README_TABLE_END!r} once each, "
                         "in that order, around the results table")
    return f"{text[:start + len(README_TABLE_START)]}\n{table}\n{text[end:]}"


def readme_table_in(text: str) -> str:
    """The table between README's markers (what :func:`with_readme_table` wrote)."""
    start = text.index(README_TABLE_START) + len(README_TABLE_START)
    return text[start:text.index(README_TABLE_END)].strip("\n")


__all__ = ["METHOD_LABELS", "README_TABLE_END", "README_TABLE_START", "add_violations_after", "bootstrap_interval",
           "claims_summary", "is_shielded", "markdown_table", "per_seed", "read_cells", "readme_table", "readme_table_in",
           "violations_after", "with_readme_table", "write_claims"]
