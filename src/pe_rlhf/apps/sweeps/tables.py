"""A sweep's summary from ``cells.csv`` rows alone: for an experiment whose cells came from several sweeps or
commits, or whose run folders are gone (the rows are what a sweep keeps of each finished cell).

``summarise_cells(sources, out, metrics)`` reads the rows of one or more ``cells.csv``
(:mod:`pe_rlhf.apps.sweeps.summary`: ``cell, method, mentor, parameter, seed, status`` and the metrics), groups
them by (method, mentor, parameter) as :func:`~pe_rlhf.apps.sweeps.summary.aggregate` does (mean and 95%
bootstrap CI over the finished seeds), and writes ``summary.csv``, ``summary.md`` and ``summary.png`` (a point
and its interval per row, evaluation-only rows as dashed lines; where every trained row's parameter is one
numeric setting, ``key=value`` with the same key, a line per method and mentor against that value instead, as
the paper draws a sensitivity). With ``paired_against=PARAMETER`` each row also
gets the paired difference to that parameter's row of the same method and mentor, seed by seed (mean and 95%
bootstrap CI over the seeds both finished): the resolved differences are those whose interval excludes 0.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

from pe_rlhf.apps.sweeps.cells import NONE
from pe_rlhf.apps.sweeps.metrics import METRICS, NAN
from pe_rlhf.apps.sweeps.summary import (SUMMARY_CSV, SUMMARY_MD, aggregate, markdown_table, read_cells_csv,
                                         write_summary_csv)
from pe_rlhf.evaluation.statistics import interval_text, seed_stats

SUMMARY_PNG = "summary.png"


def read_rows(sources: str | Path | Sequence[str | Path]) -> list[dict[str, Any]]:
    """Every row of the ``cells.csv`` sources (:func:`~pe_rlhf.apps.sweeps.summary.read_cells_csv`: a source
    ``PATH:METHOD,METHOD`` keeps only those methods), metric values as floats (NaN where empty), seeds as ints."""
    rows = read_cells_csv(sources)
    for row in rows:
        for key in METRICS:
            value = row.get(key)
            row[key] = float(value) if value not in (None, "", "nan") else NAN
        row["seed"] = int(row["seed"])
    return rows


def paired_differences(rows: Sequence[dict[str, Any]], metric: str, reference: str) -> dict[tuple, dict]:
    """``{(method, mentor, parameter): seed_stats of row - reference row}`` over the seeds both finished. The
    reference row is the same method's with parameter ``reference``; a method without one (HACO as the "no
    physics" row of a PE-RLHF ablation) pairs with the one method that has it, if only one has."""
    finished = [r for r in rows if r["status"] == "finished"]
    references = [r for r in finished if r["parameter"] == reference]
    same_method = {(r["method"], r["mentor"], r["seed"]): r[metric] for r in references}
    methods_with_it = {r["method"] for r in references}
    only = {(r["mentor"], r["seed"]): r[metric] for r in references} if len(methods_with_it) == 1 else {}
    deltas: dict[tuple, list[float]] = {}
    for r in finished:
        if r["parameter"] == reference:
            continue
        base = same_method.get((r["method"], r["mentor"], r["seed"]),
                               None if r["method"] in methods_with_it else only.get((r["mentor"], r["seed"])))
        if base is not None:
            deltas.setdefault((r["method"], r["mentor"], r["parameter"]), []).append(r[metric] - base)
    return {group: seed_stats(values) for group, values in deltas.items()}


def _label(row: dict[str, Any]) -> str:
    parts = [row["method"]] + [row[a] for a in ("mentor", "parameter") if row[a] != NONE]
    return " ".join(parts)


def numeric_parameters(table: Sequence[dict[str, Any]]) -> tuple[str, dict[str, float]] | None:
    """``(key, {parameter: value})`` when every trained row's parameter is ``key=<number>`` with one key
    (``epsilon_select=-0.5``, ``warmup_steps=10000``); else None."""
    key, values = None, {}
    for row in table:
        if row["mentor"] == NONE:
            continue
        name, sep, text = str(row["parameter"]).partition("=")
        try:
            value = float(text)
        except ValueError:
            return None
        if not sep or (key is not None and name != key) or not math.isfinite(value):
            return None
        key, values[row["parameter"]] = name, value
    return (key, values) if values else None


def plot_table(path: Path, table: list[dict[str, Any]], metrics: Sequence[str]) -> Path:
    """A panel per metric: each trained row's mean and 95% CI; evaluation-only rows (no mentor) as dashed lines.
    Rows of one numeric parameter (:func:`numeric_parameters`) draw a line per method and mentor against it."""
    from pe_rlhf.apps.sweeps.plots import _ci_yerr, _panel, _pyplot  # noqa: PLC2701 - the same package

    plt = _pyplot()
    trained = [r for r in table if r["mentor"] != NONE]
    references = [r for r in table if r["mentor"] == NONE]
    cols = min(3, len(metrics))
    nrows = math.ceil(len(metrics) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.4 * cols, 3.6 * nrows), squeeze=False)
    numeric = numeric_parameters(table)
    for ax, metric in zip(axes.flat, metrics):
        if numeric is not None:
            _panel(ax, table, metric, numeric[1])
            ax.set_xlabel(numeric[0], fontsize=8)
            ax.legend(fontsize=7, frameon=False)
            continue
        shown = [r for r in trained if r[metric]["n"]]
        ax.errorbar(range(len(shown)), [r[metric]["mean"] for r in shown], yerr=_ci_yerr([r[metric] for r in shown]),
                    marker="o", capsize=3, linestyle="none", color="C0")
        for i, r in enumerate(references):
            if r[metric]["n"]:
                ax.axhline(r[metric]["mean"], linestyle="--", linewidth=1, color=f"C{i + 1}", label=_label(r))
        ax.set_xticks(range(len(shown)), [_label(r) for r in shown], rotation=30, ha="right", fontsize=7)
        ax.set_title(METRICS[metric].label, fontsize=9)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, frameon=False)
    for ax in list(axes.flat)[len(metrics):]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def summarise_cells(sources: str | Path | Sequence[str | Path], out: str | Path, metrics: Sequence[str],
                    title: str = "sweep", description: str = "", paired_against: str | None = None,
                    plot: bool = True) -> dict[str, Any]:
    """``summary.csv``, ``summary.md`` (and ``summary.png``) in ``out`` from the rows of ``sources``; returns
    ``{"table": [...], "paired": {metric: {group: stats}}}``."""
    unknown = [m for m in metrics if m not in METRICS]
    if unknown:
        raise ValueError(f"metrics {unknown}: not among {sorted(METRICS)}")
    rows = read_rows(sources)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = aggregate(rows, metrics)
    write_summary_csv(out / SUMMARY_CSV, table, metrics)
    finished = sum(r["status"] == "finished" for r in rows)
    text = [f"# {title}", ""] + ([description, ""] if description else [])
    text += [f"{finished} of {len(rows)} cells finished; mean [95% bootstrap CI] over the finished seeds.", "",
             markdown_table(table, metrics)]
    paired = {}
    if paired_against is not None:
        paired = {m: paired_differences(rows, m, paired_against) for m in metrics}
        groups = list(dict.fromkeys(g for by_group in paired.values() for g in by_group))
        lines = [f"Paired by seed against `{paired_against}` (row minus the `{paired_against}` row of the same mentor "
                 "and seed, the same method's where it has one; resolved where the interval excludes 0):", "",
                 "| method | mentor | parameter | seeds | " + " | ".join(METRICS[m].label for m in metrics) + " |",
                 "|" + "---|" * (4 + len(metrics))]
        for group in groups:
            n = max(paired[m].get(group, {"n": 0})["n"] for m in metrics)
            values = [interval_text(paired[m][group], METRICS[m].fmt) if group in paired[m] else "—" for m in metrics]
            lines.append("| " + " | ".join([*group, str(n), *values]) + " |")
        text += ["", *lines]
    if plot:
        plot_table(out / SUMMARY_PNG, table, metrics)
        text += ["", f"![summary]({SUMMARY_PNG})"]
    (out / SUMMARY_MD).write_text("\n".join(text).rstrip() + "\n")
    return {"table": table, "paired": paired}


__all__ = ["numeric_parameters", "paired_differences", "plot_table", "read_rows", "summarise_cells"]
