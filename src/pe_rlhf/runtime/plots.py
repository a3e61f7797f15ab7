"""Learning curves from a metrics CSV: a training panel and a testing panel (spec §6).

Column naming convention (what :class:`~pe_rlhf.runtime.metrics_logger.MetricsLogger`
writes and these plots read; the x axis is ``step``, environment steps):

- ``train/<name>``: training-time counters and rates, e.g.
  ``train/safety_violations_total`` (cumulative cost), ``train/takeover_count``,
  ``train/takeover_rate`` (share of steps under takeover, recent window),
  ``train/takeover_data_usage`` (mentor steps / all steps so far),
  ``train/value_takeover_count``, ``train/value_takeover_rate`` (how often the
  selector chose the mentor's action over the physics policy's),
  ``train/intervention_cost``, ``train/time_s``;
- ``loss/<term>``: optimiser losses, e.g. ``loss/qvalue``, ``loss/actor``,
  ``loss/intervention_qvalue``, ``loss/alpha`` (every ``loss/`` column is drawn);
- ``eval/<metric>_mean`` and ``eval/<metric>_std``: a test-split evaluation,
  where ``<metric>`` is a key of ``EvaluationSummary.to_dict()``
  (``episodic_return``, ``success_rate``, ``safety_violation``, ``travel_distance``,
  ``travel_velocity``, ``overtake_count``, ...); see
  :func:`~pe_rlhf.runtime.metrics_logger.flatten_eval_summary`.

Missing columns leave their subplot marked "not logged"; blank cells are skipped.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pe_rlhf.runtime.metrics_logger import STEP, read_metrics_csv  # noqa: E402

# (column, title) in the spec's order; training panel slot 6 holds every ``loss/`` column.
TRAINING_PANEL = (
    ("train/safety_violations_total", "(a) training safety violations (total)"),
    ("train/takeover_rate", "(b) takeover rate"),
    ("train/takeover_data_usage", "(c) takeover data usage"),
    ("train/value_takeover_rate", "(d) value takeover rate (mentor over physics)"),
    ("train/intervention_cost", "(e) intervention cost"),
)
LOSS_PREFIX = "loss/"
# (summary key, title): Stage I return + success; II safety + distance; III velocity + overtakes.
TESTING_PANEL = (
    ("episodic_return", "(a) episodic return"),
    ("success_rate", "(b) success rate"),
    ("safety_violation", "(c) safety violation"),
    ("travel_distance", "(d) travel distance [m]"),
    ("travel_velocity", "(e) travel velocity [km/h]"),
    ("overtake_count", "(f) overtake count"),
)
EVAL_PREFIX = "eval/"
TRAINING_PNG = "training_curves.png"
TESTING_PNG = "testing_curves.png"
WARMUP_LABEL = "end of warm-up"


def metric_series(rows: list[dict[str, float]], column: str) -> tuple[np.ndarray, np.ndarray]:
    pts = [(r[STEP], r[column]) for r in rows if STEP in r and column in r]
    if not pts:
        return np.empty(0), np.empty(0)
    a = np.asarray(sorted(pts), dtype=np.float64)
    return a[:, 0], a[:, 1]


def _baseline_value(baseline: Mapping[str, Any] | None, metric: str) -> float | None:
    """``metric``'s mean in an evaluation JSON (``{metric: {"mean", "std"}}``) or a flat dict."""
    if not baseline:
        return None
    for key in (metric, f"{EVAL_PREFIX}{metric}_mean", f"{metric}_mean"):
        value = baseline.get(key)
        if isinstance(value, Mapping):
            value = value.get("mean")
        if isinstance(value, (int, float)) and np.isfinite(value):
            return float(value)
    return None


def mark_missing(ax, name: str) -> None:
    ax.text(0.5, 0.5, f"{name}\nnot logged", ha="center", va="center", transform=ax.transAxes,
            color="0.5", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def _mark_warmup(axes, warmup_steps: float | None) -> None:
    """A dashed vertical line where warm-up (the mentor drives every step) ends, on every drawn panel;
    labelled in panel (a)'s legend."""
    if not warmup_steps or warmup_steps <= 0:
        return
    drawn = [ax for ax in axes.flat if ax.lines]
    for ax in drawn:
        ax.axvline(float(warmup_steps), color="0.4", ls="--", lw=1, label=WARMUP_LABEL)
    if drawn:
        drawn[0].legend(fontsize=8)


def _training_figure(rows, columns, warmup_steps: float | None = None):
    fig, axes = plt.subplots(2, 3, figsize=(15, 8), constrained_layout=True)
    for ax, (column, title) in zip(axes.flat, TRAINING_PANEL):
        ax.set_title(title, fontsize=10)
        x, y = metric_series(rows, column)
        if x.size == 0:
            mark_missing(ax, column)
            continue
        ax.plot(x, y, color="tab:blue", lw=1.5)
    ax = axes.flat[len(TRAINING_PANEL)]
    ax.set_title("(f) losses", fontsize=10)
    plotted = 0
    for column in columns:
        if column.startswith(LOSS_PREFIX):
            x, y = metric_series(rows, column)
            if x.size:
                ax.plot(x, y, lw=1.2, label=column[len(LOSS_PREFIX):])
                plotted += 1
    if plotted:
        ax.set_yscale("symlog", linthresh=1e-2)  # losses differ by orders of magnitude and sign
        ax.legend(fontsize=8)
    else:
        mark_missing(ax, f"{LOSS_PREFIX}*")
    _mark_warmup(axes, warmup_steps)
    return fig, axes


def testing_figure(rows, baseline, baseline_label):
    fig, axes = plt.subplots(2, 3, figsize=(15, 8), constrained_layout=True)
    for ax, (metric, title) in zip(axes.flat, TESTING_PANEL):
        ax.set_title(title, fontsize=10)
        mean_col = f"{EVAL_PREFIX}{metric}_mean"
        x, y = metric_series(rows, mean_col)
        if x.size == 0:
            mark_missing(ax, mean_col)
            continue
        ax.plot(x, y, color="tab:red", lw=1.5, marker="o", ms=3, label="agent")
        xs, std = metric_series(rows, f"{EVAL_PREFIX}{metric}_std")
        if xs.size:
            lookup = dict(zip(xs, std))
            band = np.array([lookup.get(s, np.nan) for s in x])
            ok = np.isfinite(band)
            ax.fill_between(x[ok], (y - band)[ok], (y + band)[ok], color="tab:red", alpha=0.2, lw=0)
        level = _baseline_value(baseline, metric)
        if level is not None:
            ax.axhline(level, color="0.3", ls="--", lw=1.2, label=baseline_label)
        if metric == "success_rate":
            ax.set_ylim(-0.05, 1.05)
        ax.legend(fontsize=8)
    return fig, axes


def save_figure(fig, axes, path: Path, suptitle: str) -> Path:
    for ax in axes[-1]:
        ax.set_xlabel("environment steps")
    fig.suptitle(suptitle)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)  # a watcher never sees half a PNG
    return path


def plot_learning_curves(
    csv_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    baseline: Mapping[str, Any] | str | os.PathLike | None = None,
    baseline_label: str | None = None,
    warmup_steps: float | None = None,
) -> dict[str, Path]:
    """Write ``training_curves.png`` and ``testing_curves.png`` (2x3 panels each) to ``out_dir``.

    In: a metrics CSV (naming convention in the module docstring); an optional
    baseline drawn as dashed horizontal lines on the testing panel: an evaluation
    summary dict / JSON path (``{metric: {"mean", "std"}}``, e.g. IDM-MOBIL's) or a
    flat ``{"eval/<metric>_mean": x}`` dict; its label (default: the JSON's ``policy``);
    ``warmup_steps`` (``collector.warmup_steps``), marked on the training panel as a dashed line.
    Out: ``{"training": path, "testing": path}``; a panel none of whose columns
    were logged is not written and not returned.
    """
    columns, rows = read_metrics_csv(csv_path)
    if baseline is not None and not isinstance(baseline, Mapping):
        baseline = json.loads(Path(baseline).read_text())
    label = baseline_label or (baseline or {}).get("policy") or "baseline"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    present = {c for r in rows for c in r}
    written: dict[str, Path] = {}
    if any(c in present for c, _ in TRAINING_PANEL) or any(c.startswith(LOSS_PREFIX) for c in present):
        fig, axes = _training_figure(rows, columns, warmup_steps)
        written["training"] = save_figure(fig, axes, out_dir / TRAINING_PNG, "Training")
    if any(f"{EVAL_PREFIX}{m}_mean" in present for m, _ in TESTING_PANEL):
        fig, axes = testing_figure(rows, baseline, str(label))
        written["testing"] = save_figure(fig, axes, out_dir / TESTING_PNG, "Testing (test split, mean ± std)")
    return written
