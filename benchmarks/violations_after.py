"""A sweep's cells.csv with each cell's training safety violations after an env step (a collapsing mentor's
switch, or the end of the warm-up), for the claims summary.

    python benchmarks/violations_after.py runs/sweeps/claims_collapsing --after 15000 \
        --out docs/results/claims/cells_collapsing.csv
    python benchmarks/claims_summary.py docs/results/claims/cells_collapsing.csv ...

Writes a copy of ``SWEEP/cells.csv`` with a ``train_violations_after`` column, read from each cell's
``metrics.csv`` (``train/safety_violations_total`` at the end less its value at the last row at or before
``--after``); ``benchmarks/claims_summary.py`` then reports it as ``train_violations_after``. Prints one line a cell.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from pe_rlhf.apps.sweeps.claims import add_violations_after


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="a sweep's output folder (holds cells.csv and one folder a cell)")
    parser.add_argument("--after", type=int, required=True, help="env step: count the violations logged after it")
    parser.add_argument("--out", type=Path, required=True, help="the cells.csv to write")
    args = parser.parse_args(argv)
    if args.after < 0:
        parser.error(f"--after {args.after}: must be >= 0 (an env step)")
    try:
        rows = add_violations_after(args.sweep, args.after, args.out)
    except FileNotFoundError as err:
        parser.error(f"{err} (run the sweep first)")
    for r in rows:
        value = r["train_violations_after"]
        print(f"{r['cell']}: {'—' if math.isnan(value) else f'{value:.0f}'} "
              f"training violations after step {args.after}")
    return rows


if __name__ == "__main__":
    main()
