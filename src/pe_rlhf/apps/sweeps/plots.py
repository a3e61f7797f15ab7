"""A sweep folder's plots.

- ``summary.png``: one panel per summary metric, the mean over seeds with its 95% CI as error bars, against
  the parameter axis (its values when it is one numeric key, else its labels), one line per method x mentor;
  a row without a parameter (IDM-MOBIL, HACO in an epsilon sweep) is a dashed level across the panel.
  Without a parameter axis: bars per method x mentor.
- ``value_takeover_rate.png`` / ``takeover_rate.png``: the logged training curves (``metrics.csv``: the
  cumulative value-takeover rate, the per-batch takeover rate) against env steps, one panel per mentor, one
  line per method x parameter, mean over the seeds.
- ``value_takeover_window.png``: the value-takeover rate over the last 10 online batches
  (:func:`windowed_value_takeover_rate`), where a change over training shows (the cumulative rate hides it);
  ``mentor_fatigue.png``: the simulated mentor's fatigue multiplier, when the runs logged it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pe_rlhf.apps.sweeps.cells import NONE, Cell, cell_dir
from pe_rlhf.apps.sweeps.metrics import METRICS

CURVES = {"value_takeover_rate": ("train/value_takeover_rate", "value-takeover rate (cumulative)"),
          "takeover_rate": ("train/takeover_rate", "takeover rate (per batch)"),
          "value_takeover_window": ("windowed_value_takeover_rate", "value-takeover rate (last 10 batches)"),
          "mentor_fatigue": ("train/mentor_fatigue", "mentor fatigue (x noise and error rate)")}
WINDOW = 10  # batches in the windowed value-takeover rate


def windowed_value_takeover_rate(rows: Sequence[dict[str, float]], warmup_steps: float,
                                 window: int = WINDOW) -> dict[float, float]:
    """``{env_steps: mentor-chosen steps / takeover steps}`` over the last ``window`` online batches.

    From a run's ``metrics.csv`` rows (one per batch): a batch's takeover steps are its
    ``train/takeover_rate`` times its env steps, its mentor-chosen steps the change of the cumulative
    ``train/value_takeover_count``. Batches that began before ``warmup_steps`` are left out (the selector
    does not run in the warm-up); a window without takeover steps is left out too.
    """
    batches, previous_steps, previous_count = [], 0.0, 0.0
    for row in rows:
        if not {"env_steps", "train/takeover_rate", "train/value_takeover_count"} <= row.keys():
            continue
        steps, count = row["env_steps"], row["train/value_takeover_count"]
        if previous_steps >= warmup_steps:
            batches.append((steps, row["train/takeover_rate"] * (steps - previous_steps), count - previous_count))
        previous_steps, previous_count = steps, count
    out = {}
    for i in range(len(batches)):
        recent = batches[max(0, i - window + 1): i + 1]
        takeover = sum(b[1] for b in recent)
        if takeover > 0:
            out[batches[i][0]] = sum(b[2] for b in recent) / takeover
    return out


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _numeric_x(cells: Sequence[Cell]) -> dict[str, float] | None:
    """parameter label -> its value, when every parameterised cell sets one numeric key; else None."""
    xs: dict[str, float] = {}
    for cell in cells:
        if cell.parameter == NONE:
            continue
        if len(cell.values) != 1 or isinstance(cell.values[0][1], bool) \
                or not isinstance(cell.values[0][1], (int, float)):
            return None
        xs[cell.parameter] = float(cell.values[0][1])
    return xs or None


def _series_label(row: dict[str, Any]) -> str:
    return row["method"] if row["mentor"] == NONE else f"{row['method']} ({row['mentor']})"


def _ci_yerr(stats: Sequence[dict]) -> list[list[float]]:
    """Matplotlib's asymmetric ``yerr`` (below, above the mean) from ``{mean, lo, hi, n}`` stats; 0 without data."""
    below = [s["mean"] - s["lo"] if s["n"] else 0.0 for s in stats]
    above = [s["hi"] - s["mean"] if s["n"] else 0.0 for s in stats]
    return [below, above]


def _panel(ax, table: list[dict], metric: str, positions: dict[str, float], connect: bool = True) -> None:
    """One metric: a series per method (and mentor) against the parameter; ``connect=False`` (named variants,
    an axis without order) draws the points without joining lines."""
    series: dict[str, list[dict]] = {}
    for row in table:
        series.setdefault(_series_label(row), []).append(row)
    for i, (label, rows) in enumerate(series.items()):  # one colour per series, the same in every panel
        color = f"C{i % 10}"
        points = sorted(((positions[r["parameter"]], r[metric]) for r in rows
                         if r["parameter"] in positions and r[metric]["n"]), key=lambda point: point[0])
        if points:
            ax.errorbar([p for p, _ in points], [s["mean"] for _, s in points], yerr=_ci_yerr([s for _, s in points]),
                        marker="o", capsize=3, label=label, color=color, linestyle="-" if connect else "none")
        for r in rows:
            if r["parameter"] == NONE and r[metric]["n"]:
                ax.axhline(r[metric]["mean"], linestyle="--", linewidth=1, label=label, color=color)
    ax.set_title(METRICS[metric].label, fontsize=9)
    ax.grid(alpha=0.3)


def _bars(ax, table: list[dict], metric: str) -> None:
    labels = [_series_label(r) for r in table]
    means = [r[metric]["mean"] for r in table]  # NaN (no data) draws no bar
    ax.bar(range(len(table)), means, yerr=_ci_yerr([r[metric] for r in table]), capsize=3,
           color=[f"C{i % 10}" for i in range(len(table))])
    ax.set_xticks(range(len(table)), labels, rotation=30, ha="right", fontsize=7)
    ax.set_title(METRICS[metric].label, fontsize=9)
    ax.grid(alpha=0.3, axis="y")


def plot_summary(path: Path, cells: Sequence[Cell], table: list[dict], metrics: Sequence[str]) -> Path:
    plt = _pyplot()
    cols = min(3, len(metrics))
    rows = math.ceil(len(metrics) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    labels = list(dict.fromkeys(c.parameter for c in cells if c.parameter != NONE))
    numeric = _numeric_x(cells)
    positions = numeric or {label: float(i) for i, label in enumerate(labels)}
    for ax, metric in zip(axes.flat, metrics):
        if labels:
            _panel(ax, table, metric, positions, connect=numeric is not None)
            if numeric is None:
                ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=7)
            else:
                ax.set_xlabel(cells[[c.parameter for c in cells].index(labels[0])].values[0][0], fontsize=8)
        else:
            _bars(ax, table, metric)
    for ax in list(axes.flat)[len(metrics):]:
        ax.set_visible(False)
    legend = {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    handles, names = list(legend.values()), list(legend)
    if handles:
        fig.legend(handles, names, loc="lower center", ncol=min(4, len(handles)), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.08 if handles else 0, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_warmup_steps(run_dir: Path) -> float:
    """A run folder's ``collector.warmup_steps`` (0 without a ``config.yaml`` or without the key: a baseline
    such as HG-DAgger has no warm-up)."""
    from omegaconf import OmegaConf

    config = Path(run_dir) / "config.yaml"
    if not config.is_file():
        return 0.0
    return float(OmegaConf.select(OmegaConf.load(config), "collector.warmup_steps", default=0) or 0)


def run_curve(path: Path, column: str) -> dict[float, float]:
    """``{env_steps: value}`` of one run's ``metrics.csv``: a logged column, or ``windowed_value_takeover_rate``."""
    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    _, rows = read_metrics_csv(path)
    if column == "windowed_value_takeover_rate":
        return windowed_value_takeover_rate(rows, run_warmup_steps(Path(path).parent))
    return {r["env_steps"]: r[column] for r in rows if "env_steps" in r and column in r}


def _mean_curve(paths: list[Path], column: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Mean of ``column`` over the runs at the env steps all of them logged."""
    runs = [curve for path in paths if (curve := run_curve(path, column))]
    if not runs:
        return None
    steps = sorted(set.intersection(*(set(r) for r in runs)))
    if not steps:
        return None
    return np.array(steps), np.array([np.mean([r[s] for r in runs]) for s in steps])


def plot_curves(path: Path, out: Path, cells: Sequence[Cell], column: str, title: str) -> Path | None:
    """``column`` over training per mentor panel (None when no cell logged it)."""
    groups: dict[str, dict[str, list[Path]]] = {}
    for cell in cells:
        csv_path = cell_dir(out, cell) / "metrics.csv"
        if cell.method.trains and csv_path.is_file():
            label = cell.method.name if cell.parameter == NONE else f"{cell.method.name} {cell.parameter}"
            groups.setdefault(cell.mentor, {}).setdefault(label, []).append(csv_path)
    curves = {m: {k: c for k, p in g.items() if (c := _mean_curve(p, column)) is not None} for m, g in groups.items()}
    curves = {m: c for m, c in curves.items() if c}
    if not curves:
        return None
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(curves), figsize=(5 * len(curves), 3.4), squeeze=False, sharey=True)
    for ax, (mentor, lines) in zip(axes.flat, curves.items()):
        for label, (steps, values) in lines.items():
            ax.plot(steps, values, label=label)
        ax.set_title(f"mentor: {mentor}" if mentor != NONE else "", fontsize=9)
        ax.set_xlabel("env steps", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes.flat[0].set_ylabel(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_sweep(out: str | Path, cells: Sequence[Cell], table: list[dict], metrics: Sequence[str]) -> dict[str, Path]:
    """Every plot of the sweep folder that has data; ``{name: path}``."""
    out = Path(out)
    images = {}
    if any(r["seeds"] for r in table):
        images["summary"] = plot_summary(out / "summary.png", cells, table, metrics)
    for name, (column, title) in CURVES.items():
        path = plot_curves(out / f"{name}.png", out, cells, column, title)
        if path is not None:
            images[name] = path
    return images
