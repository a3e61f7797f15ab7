"""Issue 17's claims table: mean and 95% bootstrap CI over seeds from the claims sweep's cells.

    pe-rlhf sweep recipes/sweeps/claims.yaml --max-parallel 2 --out runs/sweeps/claims
    python benchmarks/claims_summary.py runs/sweeps/claims/cells.csv --out docs/results/claims
    python benchmarks/claims_summary.py runs/sweeps/claims/cells.csv:haco,idm-mobil \
        runs/sweeps/claims_forecast/cells.csv:pe-rlhf --out docs/results/claims   # each method from its sweep

Writes ``summary.json`` (``{claim: {method: {"success": [mean, lo, hi], "test_safety": ..., "train_violations":
..., "takeover_usage": ..., "seeds": N}}}``) and ``summary.md``; prints the table.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from pe_rlhf.apps.sweeps.claims import markdown_table, write_claims


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cells", nargs="+", help="sweep folders' cells.csv, each PATH or PATH:METHOD,METHOD")
    parser.add_argument("--out", type=Path, default=Path("docs/results/claims"))
    args = parser.parse_args(argv)
    try:
        summary = write_claims(args.cells, args.out)
    except FileNotFoundError as err:
        parser.error(f"{err} (run the claims sweep first)")
    print(markdown_table(summary))
    return summary


if __name__ == "__main__":
    main()
