"""What the critic does over training, one line per run (seed): proxy values on takeover rows against the
agent's rows, the TD error, the takeover rate and the training violations, from each run's ``metrics.csv``.

    python benchmarks/critic_curves.py runs/sweeps/learner_calibration/pe-rlhf-pv__professional__s* \
        --out docs/results/learner/critic_curves_pe-rlhf-pv.png

A ``ProxyValueLoss`` run logs ``train/q_behavior`` (Q at the executed action, takeover rows), ``train/q_agent``
(at the agent's proposal, takeover rows), ``train/q_free`` (at the executed action, the other rows) and
``train/td_error``; a ``PERLHFLoss`` run logs the first two and ``train/td_loss``. Columns a run lacks are left
out of its panel. Prints one line per run: the last row's values.
"""
from __future__ import annotations

import argparse
from pathlib import Path

PANELS = (("train/q_behavior", "Q(s, a_exec), takeover rows"), ("train/q_agent", "Q(s, a_agent), takeover rows"),
          ("train/q_free", "Q(s, a_exec), rows without a takeover"), ("train/td_error", "mean |TD error|"),
          ("train/takeover_rate", "takeover rate (batch)"), ("train/safety_violations_total", "training violations"))


def read_curves(run_dir: Path) -> dict[str, list[float]]:
    """``{column: values}`` of a run's ``metrics.csv`` (``env_steps`` included), empty cells dropped row-wise."""
    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    _, rows = read_metrics_csv(run_dir / "metrics.csv")
    columns = ["env_steps", *(c for c, _ in PANELS)]
    return {c: [float(r.get(c, float("nan"))) for r in rows] for c in columns}


def plot(curves: dict[str, dict[str, list[float]]], out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    for ax, (column, label) in zip(axes.flat, PANELS):
        for name, c in curves.items():
            ax.plot(c["env_steps"], c[column], label=name, lw=1)
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("env steps")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (each with a metrics.csv)")
    parser.add_argument("--out", type=Path, required=True, help="the figure (.png)")
    parser.add_argument("--title", default="the critic over training")
    args = parser.parse_args(argv)
    missing = [str(r) for r in args.runs if not (r / "metrics.csv").is_file()]
    if missing:
        parser.error(f"no metrics.csv in {', '.join(missing)}")
    curves = {r.name: read_curves(r) for r in args.runs}
    plot(curves, args.out, args.title)
    for name, c in curves.items():
        print(name, " ".join(f"{col.split('/')[-1]}={c[col][-1]:.3f}" for col, _ in PANELS))
    return curves


if __name__ == "__main__":
    main()
