"""``pe-rlhf compare``: the spec's Table 1 (and learning curves) from finished run folders.

    pe-rlhf compare --row PE-RLHF=runs/lanes --row HACO=runs/haco_lanes \\
        --eval IDM-MOBIL=docs/results/idm-mobil_test.json --out runs/table1
    pe-rlhf compare --glob 'runs/*/seed_*' --glob 'docs/results/idm-mobil_test.json' --out runs/table1
    pe-rlhf compare --row runs/sac_rs_s0,runs/sac_rs_s1 --row runs/lanes --out runs/t --order PE-RLHF,SAC-RS
                                                       # labels inferred from config.yaml; rows in this order
    pe-rlhf compare ... --group rl=SAC-RS,PPO-RS --group rlhf=HACO,PE-RLHF   # + one figure per group
"""

from __future__ import annotations

import argparse
import sys

from pe_rlhf.apps.compare.rows import CompareError


def run_compare(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from pe_rlhf.apps.compare import write_comparison

    order = [label.strip() for label in args.order.split(",") if label.strip()] if args.order else None
    try:
        paths, md, notes = write_comparison(args.out, runs=args.row, evaluations=args.eval, globs=args.glob,
                                            order=order, title=args.title, plot=not args.no_plot,
                                            groups=args.group)
    except CompareError as e:
        parser.error(str(e))
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    print(md, end="")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def add_compare_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf compare``: Table 1 (Markdown, CSV) and learning curves (PNG) from finished runs."""
    p = subparsers.add_parser(
        "compare", help="Table 1 and learning curves from finished run folders",
        description="Collect finished run folders (one per seed) and evaluation JSONs into the spec's Table 1: "
        "takeover data, total data, training time, training safety violations, test return, success, safety, "
        "distance, velocity, overtakes, mean [95% bootstrap CI] over seeds. Writes OUT/table.md, OUT/table.csv and "
        "OUT/learning_curves.png, and prints the table.")
    p.add_argument("--row", action="append", default=[], metavar="LABEL=DIR[,DIR...]",
                   help="a row of run folders, one per seed (a folder of run folders takes its finished "
                   "subfolders); without LABEL= the label comes from config.yaml; repeatable")
    p.add_argument("--eval", action="append", default=[], metavar="LABEL=FILE.json",
                   help="an evaluation-only row from `pe-rlhf evaluate --json` file(s) (no training columns); "
                   "without LABEL= the JSON's policy names it; repeatable")
    p.add_argument("--glob", action="append", default=[], metavar="PATTERN",
                   help="run folders / folders of runs / evaluation JSONs matching PATTERN (quote it), one row per "
                   "folder of seeds, labels inferred; repeatable")
    p.add_argument("--out", required=True, metavar="DIR", help="where table.md, table.csv and learning_curves.png go")
    p.add_argument("--order", metavar="LABEL,...", help="row order (labels); rows not named come after "
                   "(default: the paper's Table 1 order)")
    p.add_argument("--group", action="append", default=[], metavar="NAME=LABEL,...",
                   help="also draw OUT/learning_curves_NAME.png with these rows (and the evaluation-only rows "
                   "as reference levels), e.g. rl=SAC-RS,PPO-RS; repeatable")
    p.add_argument("--title", default="Table 1", help="the Markdown file's heading")
    p.add_argument("--no-plot", action="store_true", help="skip learning_curves.png")
    p.set_defaults(handler=run_compare, subparser=p)
    return p
