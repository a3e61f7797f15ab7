"""``learning_curves.png``: the compared rows' training curves against env steps (the spec's Figs. 7-13 in
kind), one panel per :data:`PANELS` entry, one line per row: the mean over its seeds with a shaded min-max
band. Seeds logged at different env steps are interpolated onto the steps inside all of their ranges.

The test panels read the periodic evaluation's ``eval/*_mean`` columns (when ``eval.every_frames`` ran) and
mark each trained row's final test value (mean over seeds, ``final_eval.json``) at its last env step; an
evaluation-only row (IDM-MOBIL) is a dashed level. Rows that take no env steps (BC, CQL: offline learners)
have no curve; their final test value is a dotted level.
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from pe_rlhf.apps.compare.rows import TRAINED, Row

LEARNING_CURVES_PNG = "learning_curves.png"
# (metrics.csv column, panel title, final_eval.json key for the final test mark / evaluation rows' level)
# and the moving-average window (logged rows) each run's curve is smoothed with before averaging
PANELS = (
    ("eval/success_rate_mean", "test success rate", "success_rate", 1),
    ("eval/episodic_return_mean", "test episodic return", "episodic_return", 1),
    ("eval/safety_violation_mean", "test safety violation", "safety_violation", 1),
    ("train/safety_violations_total", "training safety violations (cumulative)", None, 1),
    ("train/takeover_rate", "takeover rate (per batch, moving average of 10)", None, 10),
    ("train/takeover_data_usage", "takeover data usage (cumulative)", None, 1),
)


@lru_cache(maxsize=128)
def _read_rows(csv_path: Path, mtime_ns: int, size: int) -> tuple[dict[str, float], ...]:
    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    return tuple(read_metrics_csv(csv_path)[1])


def _csv_rows(csv_path: Path) -> tuple[dict[str, float], ...]:
    """The rows of ``csv_path``, read once per version of the file (a rewritten file is read again)."""
    stat = Path(csv_path).stat()
    return _read_rows(Path(csv_path), stat.st_mtime_ns, stat.st_size)


def _run_curve(csv_path: Path, column: str, window: int = 1) -> tuple[np.ndarray, np.ndarray] | None:
    rows = _csv_rows(csv_path)
    points = sorted((r["env_steps"], r[column]) for r in rows if "env_steps" in r and column in r
                    and math.isfinite(r[column]))
    if not points or points[-1][0] <= 0:
        return None
    steps, values = (np.asarray(v, float) for v in zip(*dict(points).items()))  # the last value per env step
    if window > 1:  # trailing moving average (the first points average what there is)
        sums = np.cumsum(np.concatenate([[0.0], values]))
        starts = np.maximum(np.arange(1, len(values) + 1) - window, 0)
        values = (sums[1:] - sums[starts]) / (np.arange(1, len(values) + 1) - starts)
    return steps, values


def row_curve(row: Row, column: str, window: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """``(steps, mean, min, max)`` of ``column`` over the row's seeds (each smoothed over ``window`` logged
    rows); None when no seed logged it."""
    curves = [c for s in row.sources
              if s.metrics_csv is not None and (c := _run_curve(s.metrics_csv, column, window))]
    if not curves:
        return None
    lo, hi = max(c[0][0] for c in curves), min(c[0][-1] for c in curves)
    steps = np.unique(np.concatenate([c[0] for c in curves]))
    steps = steps[(steps >= lo) & (steps <= hi)]
    if steps.size == 0:
        return None
    values = np.stack([np.interp(steps, x, y) for x, y in curves])
    return steps, values.mean(0), values.min(0), values.max(0)


def _final(row: Row, key: str) -> float:
    values = [float(s.final[key]["mean"]) for s in row.sources if isinstance(s.final.get(key), dict)
              and s.final[key].get("mean") is not None]
    return float(np.mean(values)) if values else math.nan


def _last_step(row: Row) -> float:
    steps = [c[0][-1] for s in row.sources if s.metrics_csv is not None
             and (c := _run_curve(s.metrics_csv, "env_steps"))]
    return float(np.mean(steps)) if steps else math.nan


def plot_learning_curves(path: str | Path, rows: list[Row], title: str | None = None) -> Path:
    """Draw :data:`PANELS` for ``rows`` into ``path`` (a panel without data says so); ``title`` heads the
    figure's caption line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    path = Path(path)
    cols = 3
    lines = math.ceil(len(PANELS) / cols)
    fig, axes = plt.subplots(lines, cols, figsize=(4.6 * cols, 3.5 * lines + 0.3 * math.ceil(len(rows) / 5)),
                             squeeze=False)
    colors = [f"C{i}" for i in range(len(rows))] if len(rows) <= 10 else \
        [plt.get_cmap("tab20")(i % 20) for i in range(len(rows))]
    last_steps = {row.label: _last_step(row) for row in rows if row.kind == TRAINED}
    finite_steps = [x for x in last_steps.values() if math.isfinite(x)]
    for ax, (column, panel_title, final_key, window) in zip(axes.flat, PANELS):
        drawn = False
        for row, color in zip(rows, colors):
            if row.kind != TRAINED:
                level = _final(row, final_key) if final_key else math.nan
                if math.isfinite(level):
                    ax.axhline(level, color=color, linestyle="--", linewidth=1.2)
                    drawn = True
                continue
            curve = row_curve(row, column, window)
            if curve is not None:
                steps, mean, low, high = curve
                ax.plot(steps, mean, color=color, linewidth=1.4)
                if len(row.sources) > 1:
                    ax.fill_between(steps, low, high, color=color, alpha=0.2, linewidth=0)
                drawn = True
            final = _final(row, final_key) if final_key else math.nan
            if math.isfinite(final) and math.isfinite(last_steps[row.label]):
                ax.plot([last_steps[row.label]], [final], marker="o", color=color, linestyle="none")
                drawn = True
            elif math.isfinite(final):  # an offline row: no env steps to place a dot at
                ax.axhline(final, color=color, linestyle=":", linewidth=1.4)
                drawn = True
        ax.set_title(panel_title, fontsize=9)
        ax.set_xlabel("env steps", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        if finite_steps:
            ax.set_xlim(0, max(finite_steps) * 1.03)
        if not drawn:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="0.5")
    for ax in list(axes.flat)[len(PANELS):]:
        ax.set_visible(False)
    def style(row: Row) -> str:
        if row.kind != TRAINED:
            return "--"
        return "-" if math.isfinite(last_steps[row.label]) else ":"

    handles = [Line2D([], [], color=color, linestyle=style(row)) for row, color in zip(rows, colors)]
    fig.legend(handles, [row.label for row in rows], loc="lower center", ncol=min(5, len(rows)), fontsize=8,
               frameon=False)
    fig.suptitle(f"{title + ': ' if title else ''}learning curves, mean over seeds, band min-max; dot: final test; "
                 "dashed: evaluation-only row; dotted: offline row's final test",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0.04 + 0.03 * math.ceil(len(rows) / 5), 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
