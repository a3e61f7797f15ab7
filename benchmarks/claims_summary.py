"""Issue 17's claims table: mean and 95% bootstrap CI over seeds from the claims sweep's cells.

    pe-rlhf sweep recipes/sweeps/claims.yaml --max-parallel 2 --out runs/sweeps/claims
    python benchmarks/claims_summary.py runs/sweeps/claims/cells.csv --out docs/results/claims
    python benchmarks/claims_summary.py runs/sweeps/claims/cells.csv:haco,idm-mobil \
        runs/sweeps/claims_forecast/cells.csv:pe-rlhf --out docs/results/claims   # each method from its sweep
    python benchmarks/claims_summary.py --readme    # README's results table from docs/results/claims/summary.json

Writes ``summary.json`` (``{claim: {method: {"success": [mean, lo, hi], "test_safety": ..., "train_violations":
..., "takeover_usage": ..., "seeds": N, "per_seed": ...}}}``; where the sweep shielded its cells, also
``"shielded_success"``, ``"shielded_test_safety"``, ``"override_share"``) and ``summary.md``; prints the table. With ``--readme [README.md]``
it also rewrites README's results table (``pe_rlhf.apps.sweeps.claims.readme_table``, between its two
``<!-- claims-table: ... -->`` lines) from the summary; with no cells it reads ``OUT/summary.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from pe_rlhf.apps.sweeps.claims import markdown_table, readme_table, with_readme_table, write_claims


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cells", nargs="*", help="sweep folders' cells.csv, each PATH or PATH:METHOD,METHOD")
    parser.add_argument("--out", type=Path, default=Path("docs/results/claims"))
    parser.add_argument("--readme", type=Path, nargs="?", const=Path("README.md"), default=None,
                        help="rewrite this README's results table from the summary (default README.md)")
    args = parser.parse_args(argv)
    if not args.cells and args.readme is None:
        parser.error("give the sweeps' cells.csv, or --readme to rewrite README's table from OUT/summary.json")
    try:
        summary = (write_claims(args.cells, args.out) if args.cells
                   else json.loads((args.out / "summary.json").read_text()))
    except FileNotFoundError as err:
        parser.error(f"{err} (run the claims sweep first)")
    if args.readme is not None:
        try:
            args.readme.write_text(with_readme_table(args.readme.read_text(), readme_table(summary)))
        except (OSError, ValueError) as err:
            parser.error(f"{args.readme}: {err}")
        print(f"{args.readme}: results table rewritten from {args.out / 'summary.json'}")
    print(markdown_table(summary))
    return summary


if __name__ == "__main__":
    main()
