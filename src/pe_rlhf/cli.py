"""The ``pe-rlhf`` command line: ``pe-rlhf evaluate ...`` (more subcommands register in SUBCOMMANDS).

Example::

    pe-rlhf evaluate --policy idm-mobil --split test --episodes 50 --json runs/idm.json
    pe-rlhf evaluate --policy random --seeds 2000-2049 --config-override traffic_density=0.8
"""

from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import fields
from typing import Any, Callable, Sequence

from pe_rlhf.envs import DrivingConfig, parse_seeds, scene_seeds

AddParser = Callable[[argparse._SubParsersAction], argparse.ArgumentParser]


def _literal(text: str) -> Any:
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text  # bare words such as ``split=test`` stay strings


def parse_config_overrides(pairs: Sequence[str]) -> DrivingConfig:
    """``["key=value", ...]`` -> a validated DrivingConfig; raises ValueError naming the bad field."""
    fields_by_name = {f.name: f for f in fields(DrivingConfig)}
    defaults = DrivingConfig()
    values: dict[str, Any] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--config-override {pair!r}: expected key=value")
        if key not in fields_by_name:
            raise ValueError(f"--config-override: unknown DrivingConfig field {key!r}; "
                             f"known: {', '.join(sorted(fields_by_name))}")
        value, default = _literal(raw.strip()), getattr(defaults, key)
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif isinstance(default, tuple) and isinstance(value, (str, list, tuple)):
            value = tuple(v.strip() for v in value.split(",")) if isinstance(value, str) else tuple(value)
        nullable = "None" in str(fields_by_name[key].type)
        if not (isinstance(value, type(default)) and not isinstance(value, bool)) and not (
            value is None and nullable
        ):
            raise ValueError(f"--config-override {key}={raw!r}: expected {type(default).__name__}"
                             f"{' or None' if nullable else ''}, got {type(value).__name__}")
        values[key] = value
    return DrivingConfig.from_dict(values)


def _seeds(args: argparse.Namespace) -> list[int]:
    seeds = list(parse_seeds(args.seeds) if args.seeds else scene_seeds(args.split))
    if args.episodes is not None:
        if not 1 <= args.episodes <= len(seeds):
            source = f"--seeds {args.seeds}" if args.seeds else f"split {args.split!r}"
            raise ValueError(f"--episodes {args.episodes}: {source} has {len(seeds)} seeds (need 1..{len(seeds)})")
        seeds = seeds[: args.episodes]
    if not seeds:
        raise ValueError("no scene seeds to evaluate")
    return seeds


def run_evaluate(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Evaluate one registered policy, print the stage table, write JSON if asked."""
    from pe_rlhf.evaluation import evaluate, make_policy, print_summary, write_json

    try:
        config = parse_config_overrides(args.config_override)
        seeds = _seeds(args)
        policy = make_policy(args.policy, args.seed)
    except ValueError as e:
        parser.error(str(e))
    summary = evaluate(policy, seeds, config, progress=not args.no_progress, name=args.policy).to_dict()
    print_summary(summary)
    if args.json:
        print(f"wrote {write_json(args.json, summary)}")
    return 0


def add_evaluate_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf evaluate``: run a policy on a scene split and report the spec's metrics."""
    p = subparsers.add_parser("evaluate", help="evaluate a policy on fixed scenes",
                              description="Evaluate a registered policy, one episode per scene seed.")
    p.add_argument("--policy", default="idm-mobil", help="registered policy name (idm-mobil, idm-mobil-oracle, "
                   "random, ...)")
    p.add_argument("--split", default="test", choices=("train", "test"), help="scene split (default: test)")
    p.add_argument("--seeds", help="scene seeds 'A-B' or 'a,b,c'; replaces --split")
    p.add_argument("--episodes", type=int, help="evaluate the first N seeds (default: all)")
    p.add_argument("--seed", type=int, default=0, help="policy seed (random policies)")
    p.add_argument("--config-override", action="append", default=[], metavar="KEY=VALUE",
                   help="DrivingConfig field override, repeatable (e.g. traffic_density=0.8)")
    p.add_argument("--json", metavar="PATH", help="write the summary JSON here")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(handler=run_evaluate, subparser=p)
    return p


SUBCOMMANDS: dict[str, AddParser] = {"evaluate": add_evaluate_parser}


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with one subparser per entry of :data:`SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(prog="pe-rlhf", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in SUBCOMMANDS.values():
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: sys.argv[1:]) and run the chosen subcommand; returns its exit code."""
    args = build_parser().parse_args(argv)
    return args.handler(args, args.subparser)


if __name__ == "__main__":
    sys.exit(main())
