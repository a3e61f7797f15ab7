"""An experiment's table from ``cells.csv`` rows (issue 21's grid): mean and 95% bootstrap CI over seeds per
method, mentor and parameter, optionally paired by seed against one parameter; ``summary.md``, ``summary.csv``
and ``summary.png`` in ``--out`` (:func:`pe_rlhf.apps.sweeps.tables.summarise_cells`).

    python benchmarks/grid_summary.py docs/results/claims/physics_ablation/cells.csv \
        --out docs/results/claims/physics_ablation --title "Physics ablation" --paired-against idm+mobil
"""
from __future__ import annotations

import argparse

from pe_rlhf.apps.sweeps.metrics import METRICS
from pe_rlhf.apps.sweeps.tables import summarise_cells

DEFAULT = ["success_rate", "safety_violation", "train_safety_violations", "takeover_data_usage",
           "value_takeover_rate", "travel_velocity"]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cells", nargs="+", help="cells.csv files (a sweep's, or rows merged by hand); "
                        "PATH:METHOD,METHOD keeps only those methods of PATH")
    parser.add_argument("--out", required=True)
    parser.add_argument("--title", default="sweep")
    parser.add_argument("--description", default="")
    parser.add_argument("--metrics", default=",".join(DEFAULT), help=f"comma-separated, of {', '.join(METRICS)}")
    parser.add_argument("--paired-against", default=None, metavar="PARAMETER")
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args(argv)
    metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
    try:
        result = summarise_cells(args.cells, args.out, metrics, args.title, args.description, args.paired_against,
                                 plot=not args.no_plot)
    except (FileNotFoundError, ValueError) as err:
        parser.error(str(err))
    print(open(f"{args.out}/summary.md").read())
    return result


if __name__ == "__main__":
    main()
