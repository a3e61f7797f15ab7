"""A baseline run's learning curves from its ``metrics.csv`` (column names of :mod:`pe_rlhf.runtime.plots`).

``learning_curves.png``: training episode return and cost (the cost limit dashed), cumulative safety
violations, training success rate, ``lambda`` (or CPO's constraint violation ``c = J_c - limit``; the
imitation baselines: takeover rate, takeover data usage, the mentor's share of the data, GAIL's mean
``D(s, a)`` on the policy's and the mentor's steps) and the losses; ``testing_curves.png``
(:mod:`pe_rlhf.runtime.plots`' test panel) when periodic evaluations
were logged.
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from pe_rlhf.runtime.metrics_logger import read_metrics_csv
from pe_rlhf.runtime.plots import (
    EVAL_PREFIX,
    LOSS_PREFIX,
    TESTING_PANEL,
    TESTING_PNG,
    mark_missing,
    save_figure,
    metric_series,
    testing_figure,
)

LEARNING_PNG = "learning_curves.png"
# (columns drawn together, title); a column's label is its name after the prefix.
LEARNING_PANEL = (
    (("train/episode_return", "eval/episodic_return_mean"), "(a) episode return (train, test)"),
    (("train/episode_cost", "train/episode_cost_window"), "(b) episode cost (train)"),
    (("train/safety_violations_total",), "(c) training safety violations (total)"),
    (("train/success_rate_total", "eval/success_rate_mean"), "(d) success rate (train total, test)"),
    (("train/lambda", "train/cpo_constraint_violation", "train/kl_coef", "train/takeover_rate",
      "train/takeover_data_usage", "train/mentor_data_share", "train/d_policy", "train/d_expert"),
     "(e) lambda / CPO c / KL coef / takeovers / GAIL D"),
)


def plot_baseline_curves(csv_path: str | os.PathLike, out_dir: str | os.PathLike,
                         cost_limit: float | None = None, steps_are_updates: bool = False) -> dict[str, Path]:
    """Write ``learning_curves.png`` (and ``testing_curves.png`` if eval columns exist) to ``out_dir``;
    returns ``{"learning": path[, "testing": path]}``. ``steps_are_updates``: the offline methods' rows are
    counted in gradient updates (the titles say so; the shared axis label says environment steps)."""
    unit = " (x: gradient updates, no env steps)" if steps_are_updates else ""
    columns, rows = read_metrics_csv(csv_path)
    out_dir = Path(out_dir)
    fig, axes = plt.subplots(2, 3, figsize=(15, 8), constrained_layout=True)
    for ax, (cols, title) in zip(axes.flat, LEARNING_PANEL):
        ax.set_title(title, fontsize=10)
        drawn = 0
        for column in cols:
            x, y = metric_series(rows, column)
            if x.size:
                ax.plot(x, y, lw=1.4, marker="o" if x.size < 30 else None, ms=3, label=column.split("/", 1)[1])
                drawn += 1
        if not drawn:
            mark_missing(ax, " | ".join(cols))
            continue
        if cols[0] == "train/success_rate_total":
            ax.set_ylim(-0.05, 1.05)
        if cost_limit is not None and cols[0] == "train/episode_cost":
            ax.axhline(cost_limit, color="0.3", ls="--", lw=1.2, label="cost limit")
        ax.legend(fontsize=8)
    ax = axes.flat[len(LEARNING_PANEL)]
    ax.set_title("(f) losses", fontsize=10)
    losses = [c for c in columns if c.startswith(LOSS_PREFIX)]
    for column in losses:
        x, y = metric_series(rows, column)
        if x.size:
            ax.plot(x, y, lw=1.2, label=column[len(LOSS_PREFIX):])
    if losses:
        ax.set_yscale("symlog", linthresh=1e-2)  # losses differ by orders of magnitude and sign
        ax.legend(fontsize=8)
    else:
        mark_missing(ax, f"{LOSS_PREFIX}*")
    written = {"learning": save_figure(fig, axes, out_dir / LEARNING_PNG, f"Training{unit}")}
    if any(metric_series(rows, f"{EVAL_PREFIX}{m}_mean")[0].size for m, _ in TESTING_PANEL):
        fig, axes = testing_figure(rows, None, "baseline")
        written["testing"] = save_figure(fig, axes, out_dir / TESTING_PNG, f"Testing (test split, mean ± std){unit}")
    return written
