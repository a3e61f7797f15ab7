"""Value-takeover analysis (the paper's Fig. 18 in kind): how often the selector executes the mentor's action
over training, per run, with the simulated mentor's fatigue when the run logged it.

    python benchmarks/value_takeover_curves.py LABEL=RUN_DIR [LABEL=RUN_DIR ...] --out FIG.png [--json out.json]
    python benchmarks/value_takeover_curves.py professional=runs/lanes/seed_0 \\
        amateur=runs/sweeps/mentor_proficiency/pe-rlhf__amateur__s0 --out docs/results/value_takeover.png

Left panel: the value-takeover rate over the last 10 online batches (1,000 env steps;
:func:`pe_rlhf.apps.sweeps.plots.windowed_value_takeover_rate`), right: the cumulative rate the recipe logs, with
``train/mentor_fatigue`` on a second axis where logged. ``--json`` writes each run's windowed curve and its
mean over the first and the last third of the online phase.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pe_rlhf.apps.sweeps.plots import run_curve, run_warmup_steps


def run_curves(run: Path) -> dict:
    """``{"window": {steps: rate}, "cumulative": {...}, "fatigue": {...}, "first_third", "last_third"}``."""
    warmup, metrics = run_warmup_steps(run), run / "metrics.csv"
    window = run_curve(metrics, "windowed_value_takeover_rate")
    out = {"window": window,
           "cumulative": {s: v for s, v in run_curve(metrics, "train/value_takeover_rate").items() if s > warmup},
           "fatigue": run_curve(metrics, "train/mentor_fatigue")}
    steps = sorted(window)
    if steps:
        third = (steps[-1] - warmup) / 3
        first = [window[s] for s in steps if s <= warmup + third]
        last = [window[s] for s in steps if s > steps[-1] - third]
        out["first_third"], out["last_third"] = float(np.mean(first)), float(np.mean(last))
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR (a PE-RLHF run folder)")
    parser.add_argument("--out", type=Path, required=True, help="figure path (.png)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    curves = {}
    for item in args.runs:
        label, sep, directory = item.partition("=")
        if not sep or not label or not directory:
            parser.error(f"{item!r}: expected LABEL=RUN_DIR")
        if not (Path(directory) / "metrics.csv").is_file():
            parser.error(f"{directory}: no metrics.csv (not a recipe run folder)")
        curves[label] = run_curves(Path(directory))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_w, ax_c) = plt.subplots(1, 2, figsize=(11, 3.6))
    fatigue_ax = None
    for label, c in curves.items():
        line, = ax_w.plot(sorted(c["window"]), [c["window"][s] for s in sorted(c["window"])], label=label)
        ax_c.plot(sorted(c["cumulative"]), [c["cumulative"][s] for s in sorted(c["cumulative"])], label=label,
                  color=line.get_color())
        if c["fatigue"] and max(c["fatigue"].values()) > 1.0:
            fatigue_ax = fatigue_ax or ax_c.twinx()
            fatigue_ax.plot(sorted(c["fatigue"]), [c["fatigue"][s] for s in sorted(c["fatigue"])], ls=":",
                            color=line.get_color(), label=f"{label} fatigue")
            fatigue_ax.set_ylabel("mentor fatigue (x)", fontsize=8)
    ax_w.set_title("value-takeover rate, last 10 batches", fontsize=9)
    ax_c.set_title("value-takeover rate, cumulative", fontsize=9)
    for ax in (ax_w, ax_c):
        ax.set_xlabel("env steps", fontsize=8)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    plt.close(fig)
    summary = {label: {k: v for k, v in c.items() if k in ("first_third", "last_third")} for label, c in curves.items()}
    for label, s in summary.items():
        print(f"{label}: windowed value-takeover rate {s.get('first_third', float('nan')):.2f} (first third of the "
              f"online phase) -> {s.get('last_third', float('nan')):.2f} (last third)")
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "curves": {
            label: {k: {str(s): v for s, v in c[k].items()} for k in ("window", "cumulative", "fatigue")}
            for label, c in curves.items()}}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return curves


if __name__ == "__main__":
    main()
