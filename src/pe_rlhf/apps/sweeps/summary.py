"""A sweep folder's tables: per-cell metrics (``cells.csv``) and the mean with its 95% CI over seeds per
method x mentor x parameter row (``summary.csv``, ``summary.md``).

A cell's numbers come from its ``final_eval.json`` (test metrics on ``eval.split``, the training totals)
and the last row of its ``metrics.csv`` (the cumulative training rates the recipe logs). Missing numbers
(an evaluation-only cell has no training) are NaN in the CSVs and ``—`` in the Markdown. The Markdown shows
``mean [lo, hi]``, the 95% bootstrap CI of the mean over the row's finished seeds
(:mod:`pe_rlhf.evaluation.statistics`); the CSV has ``_mean``, ``_std`` (population std, as
``benchmarks/train_seeds.py`` reports), ``_lo`` and ``_hi`` per metric.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pe_rlhf.evaluation.statistics import interval_text, seed_stats
from pe_rlhf.apps.sweeps.cells import CELL_FILE, FINAL_EVAL, NONE, SHIELDED_EVAL, Cell, cell_dir
from pe_rlhf.apps.sweeps.metrics import (  # noqa: F401 (re-exported)
    DEFAULT_METRICS, METRICS, NAN, Metric, last_csv_row, logged_metrics, metric_values)

SUMMARY_MD, SUMMARY_CSV, CELLS_CSV = "summary.md", "summary.csv", "cells.csv"


def read_cell(directory: str | Path, metrics: dict[str, Metric] = METRICS) -> dict[str, float]:
    """Every ``metrics`` value (default :data:`METRICS`) of a finished cell folder (NaN where it has none; the
    shielded ones read its ``shielded_eval.json``); {} if unfinished."""
    directory = Path(directory)
    if not (directory / FINAL_EVAL).is_file():
        return {}
    final = json.loads((directory / FINAL_EVAL).read_text())
    if (directory / SHIELDED_EVAL).is_file():
        final["shielded"] = json.loads((directory / SHIELDED_EVAL).read_text())
    return metric_values(final, last_csv_row(directory / "metrics.csv"), metrics)


def cell_rows(out: str | Path, cells: Sequence[Cell]) -> list[dict[str, Any]]:
    """One dict per cell: name, method, mentor, parameter, seed, status and every metric."""
    rows = []
    for cell in cells:
        directory = cell_dir(Path(out), cell)
        values = read_cell(directory)
        status = "finished" if values else ("unfinished" if (directory / CELL_FILE).is_file() else "not started")
        rows.append({"cell": cell.name, "method": cell.method.name, "mentor": cell.mentor,
                     "parameter": cell.parameter, "seed": cell.seed, "status": status,
                     **{k: values.get(k, NAN) for k in METRICS}})
    return rows


def read_cells_csv(sources: str | Path | Sequence[str | Path]) -> list[dict[str, str]]:
    """The rows of one or more ``cells.csv``, as written (strings). A source ``PATH:METHOD,METHOD`` keeps only
    those methods (sweep names, e.g. ``runs/sweeps/claims/cells.csv:haco,idm-mobil``), so that a table can take
    each method from the sweep that ran its final configuration."""
    rows = []
    for source in [sources] if isinstance(sources, (str, Path)) else sources:
        path, methods = Path(source), None
        if not path.is_file() and ":" in str(source):
            head, _, tail = str(source).rpartition(":")
            path, methods = Path(head), {m.strip() for m in tail.split(",") if m.strip()}
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such cells.csv")
        with open(path, newline="") as f:
            rows += [r for r in csv.DictReader(f) if methods is None or r["method"] in methods]
    return rows


def mean_std(values: Sequence[float]) -> dict[str, float]:
    """Mean and population std of the finite values, and how many there were (NaN, NaN, 0 if none)."""
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not finite:
        return {"mean": NAN, "std": NAN, "n": 0}
    return {"mean": float(np.mean(finite)), "std": float(np.std(finite)), "n": len(finite)}


def aggregate(rows: Sequence[dict[str, Any]], metrics: Sequence[str]) -> list[dict[str, Any]]:
    """Rows grouped by (method, mentor, parameter) in first-seen order; per metric ``{mean, std, lo, hi, n}``
    (:func:`~pe_rlhf.evaluation.statistics.seed_stats`) over the finished seeds; ``seeds`` finished / ``cells``
    in the group."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["method"], row["mentor"], row["parameter"]), []).append(row)
    table = []
    for (method, mentor, parameter), members in groups.items():
        done = [r for r in members if r["status"] == "finished"]
        table.append({"method": method, "mentor": mentor, "parameter": parameter, "seeds": len(done),
                      "cells": len(members), **{m: seed_stats([r[m] for r in done]) for m in metrics}})
    return table


def write_csv(path: Path, header: list[str], rows: list[list[Any]]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def markdown_table(table: list[dict[str, Any]], metrics: Sequence[str]) -> str:
    """The summary as a Markdown table; the mentor / parameter columns only when some row has one."""
    axes = [a for a in ("mentor", "parameter") if any(r[a] != NONE for r in table)]
    header = ["method", *axes, "seeds", *(METRICS[m].label for m in metrics)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in table:
        cells = [r["method"], *(r[a] for a in axes), f"{r['seeds']}/{r['cells']}",
                 *(interval_text(r[m], METRICS[m].fmt) for m in metrics)]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def write_summary_csv(path: Path, table: list[dict[str, Any]], metrics: Sequence[str]) -> None:
    """The aggregated table (:func:`aggregate`) as CSV: group columns, then ``<metric>_{mean,std,lo,hi}``."""
    header = ["method", "mentor", "parameter", "seeds", "cells"]
    stats = ("mean", "std", "lo", "hi")
    write_csv(path, header + [f"{m}_{s}" for m in metrics for s in stats],
              [[r[k] for k in header] + [r[m][s] for m in metrics for s in stats] for r in table])


def write_summary(out: str | Path, cells: Sequence[Cell], metrics: Sequence[str], title: str = "sweep",
                  description: str = "", plots: bool = True) -> dict[str, Path]:
    """``cells.csv``, ``summary.csv``, ``summary.md`` (and the plots, :mod:`pe_rlhf.apps.sweeps.plots`) in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = cell_rows(out, cells)
    keys = ["cell", "method", "mentor", "parameter", "seed", "status", *METRICS]
    write_csv(out / CELLS_CSV, keys, [[r[k] for k in keys] for r in rows])
    table = aggregate(rows, metrics)
    write_summary_csv(out / SUMMARY_CSV, table, metrics)
    finished = sum(r["status"] == "finished" for r in rows)
    text = [f"# Sweep {title}", ""] + ([description, ""] if description else [])
    text += [(f"{finished} of {len(rows)} cells finished; mean [95% bootstrap CI] over the finished seeds; "
              "test metrics on the recipe's eval split, training numbers as logged at the end of training."), "",
             markdown_table(table, metrics)]
    paths = {"cells": out / CELLS_CSV, "summary_csv": out / SUMMARY_CSV, "summary_md": out / SUMMARY_MD}
    if plots:
        from pe_rlhf.apps.sweeps.plots import plot_sweep

        images = plot_sweep(out, cells, table, metrics)
        paths.update(images)
        text += [""] + [f"![{name}]({path.name})" for name, path in images.items()]
    (out / SUMMARY_MD).write_text("\n".join(text).rstrip() + "\n")
    return paths
