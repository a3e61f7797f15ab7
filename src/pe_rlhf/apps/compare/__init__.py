"""``pe-rlhf compare``: the spec's Table 1 from finished runs, as Markdown, CSV and learning curves.

    pe-rlhf compare --row PE-RLHF=runs/lanes --row HACO=runs/haco_lanes \\
        --eval IDM-MOBIL=docs/results/idm-mobil_test.json --out runs/table1

Parts: :mod:`~pe_rlhf.apps.compare.rows` (which run folders / evaluation JSONs make each row, labels, order),
:mod:`~pe_rlhf.apps.compare.table` (the columns, read with :mod:`pe_rlhf.apps.sweeps.summary`'s readers; mean
[95% bootstrap CI] over seeds; ``table.md``, ``table.csv``), :mod:`~pe_rlhf.apps.compare.plots`
(``learning_curves.png``), :mod:`~pe_rlhf.apps.compare.groups` (a figure per group of rows) and
:mod:`~pe_rlhf.apps.compare.cli`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from pe_rlhf.apps.compare.groups import group_png, parse_group, select_group
from pe_rlhf.apps.compare.plots import LEARNING_CURVES_PNG, plot_learning_curves
from pe_rlhf.apps.compare.rows import CompareError, Row, Source, collect_rows, infer_label
from pe_rlhf.apps.compare.table import COLUMNS, aggregate_rows, markdown_table, write_table


def write_comparison(out: str | Path, runs: Sequence[str] = (), evaluations: Sequence[str] = (),
                     globs: Sequence[str] = (), order: list[str] | None = None, title: str = "Table 1",
                     plot: bool = True, groups: Sequence[str] = ()) -> tuple[dict[str, Path], str, list[str]]:
    """Collect the rows (``--row`` / ``--eval`` / ``--glob`` specs), write ``table.md``, ``table.csv`` and
    (``plot``) ``learning_curves.png`` into ``out``; returns ``({name: path}, the Markdown table, notes)``.
    Each ``groups`` spec ``NAME=LABEL,LABEL...`` also draws ``learning_curves_<name>.png`` with those rows
    and every evaluation-only row (the reference levels). CompareError naming the bad path or spec."""
    rows, notes = collect_rows(list(runs), list(evaluations), list(globs), order)
    figures = [(name, select_group(rows, labels)) for name, labels in map(parse_group, groups)]  # fail before writing
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    images = {}
    if plot:
        images["learning_curves"] = plot_learning_curves(out / LEARNING_CURVES_PNG, rows)
        for name, members in figures:
            images[f"learning_curves_{name}"] = plot_learning_curves(out / group_png(name), members, title=name)
    paths, md = write_table(out, rows, title=title, images=[(key, p.name) for key, p in images.items()],
                            notes=notes)
    return {**paths, **images}, md, notes


__all__ = ["COLUMNS", "CompareError", "Row", "Source", "aggregate_rows", "collect_rows", "infer_label",
           "markdown_table", "parse_group", "plot_learning_curves", "select_group", "write_comparison",
           "write_table"]
