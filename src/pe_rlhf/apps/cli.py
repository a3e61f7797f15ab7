"""The ``pe-rlhf`` command: evaluate policies and trained runs, record demonstrations, run sweeps, compare runs.

Subcommands (:data:`SUBCOMMANDS`): ``evaluate``, ``demo record|info|export|import``, ``sweep``, ``compare``; training
itself runs from ``recipes/<method>/train.py``. Examples in :data:`EPILOG` (``pe-rlhf --help``).

Errors: a bad value (a config override, a seed range, a run folder, a sweep or compare spec: a
``ValueError`` the subcommand checks, a :class:`~pe_rlhf.runtime.config_rules.ConfigError`) or a bad argument
prints one line ``error: <message>`` to stderr and exits 2, without a traceback; ``pe-rlhf --debug
COMMAND ...`` (also accepted after the command) or ``PE_RLHF_DEBUG=1`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import sys
from dataclasses import fields
from typing import Any, Callable, Sequence

from pe_rlhf import __version__
from pe_rlhf.errors import OneLineErrorParser, debug_requested, fail
from pe_rlhf.envs import DrivingConfig, parse_seeds, scene_seeds
from pe_rlhf.envs.splits import SPLITS

AddParser = Callable[[argparse._SubParsersAction], argparse.ArgumentParser]


def _literal(text: str) -> Any:
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text  # bare words such as ``split=test`` stay strings


def parse_config_overrides(pairs: Sequence[str], base: DrivingConfig | None = None) -> DrivingConfig:
    """``["key=value", ...]`` on top of ``base`` (default: ``DrivingConfig()``) -> a validated
    DrivingConfig; raises ValueError naming the bad field."""
    fields_by_name = {f.name: f for f in fields(DrivingConfig)}
    defaults = base or DrivingConfig()
    values: dict[str, Any] = base.to_dict() if base is not None else {}
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
        same_type = isinstance(value, bool) if isinstance(default, bool) else (
            isinstance(value, type(default)) and not isinstance(value, bool))
        if not same_type and not (value is None and nullable):
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


def _shield_threshold(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"--shield {text!r}: a threshold in seconds >= 0 (e.g. 0.5)")
    return value


def run_evaluate(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Evaluate one registered policy, print the stage table, write JSON if asked."""
    import pe_rlhf.mentors.registry  # noqa: F401  (registers professional / amateur / adversarial)
    from pe_rlhf.evaluation import evaluate, make_policy, print_summary, write_json

    try:
        seeds = _seeds(args)
        config = parse_config_overrides(args.config_override)
        if args.checkpoint:
            from pe_rlhf.evaluation import TorchRLPolicyAdapter
            from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor, run_world

            # the run's own world (observation size, traffic, ...), then the command line's overrides
            world = dataclasses.replace(run_world(args.checkpoint), split=args.split)
            config = parse_config_overrides(args.config_override, world)
            policy, name = TorchRLPolicyAdapter(load_run_actor(args.checkpoint)), f"agent:{args.checkpoint}"
        else:
            policy, name = make_policy(args.policy, args.seed), args.policy
    except (ValueError, FileNotFoundError) as e:
        parser.error(str(e))
    wrap_env = None
    if args.shield is not None:  # a runtime shield (Simplex) over the policy: docs/guide/shield.md
        from pe_rlhf.wrappers import SafetyShieldWrapper

        threshold = float(args.shield)
        wrap_env, name = (lambda env: SafetyShieldWrapper(env, threshold)), f"{name} shielded"
    summary = evaluate(policy, seeds, config, progress=not args.no_progress, name=name, wrap_env=wrap_env).to_dict()
    print_summary(summary)
    if args.shield is not None:
        latency = summary["decision_latency_ms"]
        print(f"shield: override share {summary['override_share']:.3f} of steps, decision latency "
              f"{latency['mean']:.2f} ms (std {latency['std']:.2f})")
    if args.json:
        print(f"wrote {write_json(args.json, summary)}")
    return 0


def add_evaluate_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf evaluate``: run a policy on a scene split and report the spec's metrics."""
    p = subparsers.add_parser("evaluate", help="evaluate a policy on fixed scenes",
                              description="Evaluate a registered policy, one episode per scene seed.")
    p.add_argument("--policy", default="idm-mobil", help="registered policy name (idm-mobil, idm-mobil-oracle, "
                   "random, ...)")
    p.add_argument("--checkpoint", metavar="RUN_DIR", help="evaluate the agent trained in this run folder, "
                   "PE-RLHF/HACO/HAIM-DRL or baseline (its actor.pt, or its newest checkpoint); replaces --policy")
    p.add_argument("--split", default="test", choices=tuple(SPLITS), help="scene split (default: test)")
    p.add_argument("--seeds", help="scene seeds 'A-B' or 'a,b,c'; replaces --split")
    p.add_argument("--episodes", type=int, help="evaluate the first N seeds (default: all)")
    p.add_argument("--seed", type=int, default=0, help="policy seed (random policies)")
    p.add_argument("--config-override", action="append", default=[], metavar="KEY=VALUE",
                   help="DrivingConfig field override, repeatable (e.g. traffic_density=0.8)")
    p.add_argument("--json", metavar="PATH", help="write the summary JSON here")
    p.add_argument("--shield", nargs="?", type=_shield_threshold, const=0.5, default=None, metavar="SECONDS",
                   help="drive under the runtime safety shield (physics takes over where the policy's action is "
                   "forecast to fail more than SECONDS, default 0.5, sooner than physics'); reports the override "
                   "share and the decision latency")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(handler=run_evaluate, subparser=p)
    return p


def _make_mentor(name: str, seed: int):
    """A registered mentor by name; imported lazily (the registry pulls in the simulated drivers)."""
    try:
        from pe_rlhf.mentors.registry import make_mentor
    except ImportError as e:
        raise ValueError(f"--mentor {name!r}: the mentor registry is unavailable ({e})") from None
    try:
        return make_mentor(name, seed)
    except (KeyError, ValueError) as e:  # the registry's message lists the known names
        raise ValueError(f"--mentor {name!r}: {e}") from None


def run_demo_record(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Record (or continue) a mentor-only demonstration dataset."""
    from pe_rlhf.mentors.recording import DemonstrationRecorder, dataset_info, record

    try:
        config = parse_config_overrides(args.config_override)
        seeds = list(parse_seeds(args.seeds) if args.seeds else scene_seeds(args.split))
        if args.steps < 1:
            raise ValueError(f"--steps {args.steps}: must be >= 1")
        mentor = _make_mentor(args.mentor, args.seed)
        name = mentor.name if isinstance(getattr(mentor, "name", None), str) else args.mentor  # aliases resolved
        recorder = DemonstrationRecorder(args.out, config, name, seeds,
                                         split=None if args.seeds else args.split)
    except (ValueError, RuntimeError) as e:
        parser.error(str(e))
    with recorder:
        start = recorder.episodes
        try:
            stats = record(mentor, recorder, args.steps, exact=args.exact, progress=not args.no_progress)
        except KeyboardInterrupt:
            print(f"\ninterrupted: the episode in progress is dropped; {recorder.episodes - start} new episodes "
                  f"were saved ({recorder.episodes} in {args.out})", file=sys.stderr)
            return 130
        finally:
            getattr(mentor, "close", lambda: None)()  # the human mentor's window
    print(f"recorded {stats['episodes']} episodes ({stats['steps']} steps, {stats['steps_per_s']:.0f} steps/s) "
          f"as episodes {start}..{start + stats['episodes'] - 1} into {args.out}")
    _print_demo_info(dataset_info(args.out))
    return 0


def _print_demo_info(info: dict) -> None:
    print(f"{info['directory']}: mentor {info['mentor']}, split {info['split']}, {info['episodes']} episodes, "
          f"{info['steps']} steps, success rate {info['success_rate']:.2f}, mean return {info['mean_return']:.1f}, "
          f"mean cost {info['mean_cost']:.2f}")


def run_demo_info(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Print a demonstration dataset's summary."""
    from pe_rlhf.mentors.recording import dataset_info

    try:
        info = dataset_info(args.directory)
    except (ValueError, FileNotFoundError) as e:
        parser.error(str(e))
    _print_demo_info(info)
    return 0


def run_demo_export(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Write a demonstration dataset as a Minari dataset."""
    try:
        from pe_rlhf.mentors.minari_export import export_minari

        done = export_minari(args.directory, args.out)
    except (ValueError, FileNotFoundError, ImportError) as e:
        parser.error(str(e))
    print(f"exported {done['episodes']} episodes ({done['steps']} steps) of {args.directory} as Minari dataset "
          f"{done['dataset_id']} in {done['path']}")
    return 0


def run_demo_import(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Append a Minari dataset's episodes to a demonstration dataset."""
    from pe_rlhf.mentors.recording import dataset_info

    try:
        from pe_rlhf.mentors.minari_export import import_minari

        done = import_minari(args.source, args.out, mentor=args.mentor)
    except (ValueError, FileNotFoundError, ImportError, RuntimeError) as e:
        parser.error(str(e))
    print(f"imported {done['episodes']} episodes ({done['steps']} steps) of {args.source} into {args.out}")
    _print_demo_info(dataset_info(args.out))
    return 0


MINARI_WHERE = ("a Minari dataset id [namespace/]name-vN (under $MINARI_DATASETS_PATH, default "
                "~/.minari/datasets) or a path starting with /, . or ~ whose last part is such an id")


def add_demo_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf demo record|info|export|import``: crash-safe mentor demonstrations (warm-up data)."""
    p = subparsers.add_parser("demo", help="record, inspect, export or import mentor demonstrations",
                              description="Record mentor-only driving into a crash-safe dataset, summarise one, "
                              "or convert one to or from a Minari dataset.")
    sub = p.add_subparsers(dest="demo_command", required=True, metavar="ACTION")
    r = sub.add_parser("record", help="record (or continue) a dataset",
                       description="Let a mentor drive alone; each finished episode is saved immediately. "
                       "Re-running on the same --out continues the dataset.")
    r.add_argument("--mentor", required=True, metavar="NAME", help="professional, amateur, adversarial or human")
    r.add_argument("--split", default="train", choices=tuple(SPLITS), help="scene split to cycle through")
    r.add_argument("--seeds", help="scene seeds 'A-B' or 'a,b,c'; replaces --split")
    r.add_argument("--steps", type=int, required=True, help="env steps to record (whole episodes: may overshoot)")
    r.add_argument("--exact", action="store_true", help="stop at exactly --steps, cutting the last episode")
    r.add_argument("--out", required=True, metavar="DIR", help="dataset directory (created or continued)")
    r.add_argument("--seed", type=int, default=0, help="mentor seed")
    r.add_argument("--config-override", action="append", default=[], metavar="KEY=VALUE",
                   help="DrivingConfig field override, repeatable (must match when continuing)")
    r.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    r.set_defaults(handler=run_demo_record, subparser=r)
    i = sub.add_parser("info", help="summarise a dataset", description="Episodes, steps, success rate, mentor.")
    i.add_argument("directory", metavar="DIR")
    i.set_defaults(handler=run_demo_info, subparser=i)
    e = sub.add_parser("export", help="write a dataset in another format (Minari)",
                       description="Write a dataset as a Minari dataset that minari.load_dataset reads: "
                       "observations, executed actions, rewards, terminations/truncations; the step info as infos.")
    e.add_argument("directory", metavar="DIR")
    e.add_argument("--to", default="minari", choices=("minari",), help="format (default: minari)")
    e.add_argument("--out", required=True, metavar="NAME_OR_PATH", help=f"{MINARI_WHERE}; must not exist")
    e.set_defaults(handler=run_demo_export, subparser=e)
    m = sub.add_parser("import", help="append a dataset of another format (Minari)",
                       description="Append the episodes of a Minari dataset recorded in pe_rlhf/Driving-v0 "
                       "(e.g. one 'demo export' wrote) to a dataset directory.")
    m.add_argument("source", metavar="NAME_OR_PATH", help=MINARI_WHERE)
    m.add_argument("--from", dest="format", default="minari", choices=("minari",), help="format (default: minari)")
    m.add_argument("--out", required=True, metavar="DIR", help="dataset directory (created or continued)")
    m.add_argument("--mentor", metavar="NAME", help="the mentor's name to record (default: the dataset's)")
    m.set_defaults(handler=run_demo_import, subparser=m)
    return p


def add_sweep_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf sweep``: see :mod:`pe_rlhf.apps.sweeps.cli`."""
    from pe_rlhf.apps.sweeps.cli import add_sweep_parser as add

    return add(subparsers)


def add_compare_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf compare``: see :mod:`pe_rlhf.apps.compare.cli`."""
    from pe_rlhf.apps.compare.cli import add_compare_parser as add

    return add(subparsers)


SUBCOMMANDS: dict[str, AddParser] = {"evaluate": add_evaluate_parser, "demo": add_demo_parser,
                                     "sweep": add_sweep_parser, "compare": add_compare_parser}


DESCRIPTION = """\
PE-RLHF (physics-enhanced reinforcement learning with human feedback) for safe driving: evaluate a
policy or a trained run on fixed scenes, record mentor demonstrations, run a sweep of training runs,
and turn finished runs into the paper's table. Training itself runs from the recipes:
python recipes/<method>/train.py (e.g. recipes/pe_rlhf/train.py profile=cpu)."""
EPILOG = """\
examples:
  pe-rlhf evaluate --policy idm-mobil --split test --episodes 50 --json runs/idm.json
  pe-rlhf evaluate --checkpoint runs/pe-rlhf-20250101-120000 --seeds 1000-1049
  pe-rlhf demo record --mentor professional --steps 10000 --out runs/demos
  pe-rlhf demo info runs/demos
  pe-rlhf demo export runs/demos --to minari --out pe-rlhf/professional-v0
  pe-rlhf sweep recipes/sweeps/mentor_proficiency.yaml --max-parallel 2
  pe-rlhf compare --row HACO=runs/haco --eval IDM-MOBIL=runs/idm.json --out runs/table1

'pe-rlhf COMMAND --help' lists a command's options. A bad value or argument prints one line
'error: ...' and exits 2; add --debug (or set PE_RLHF_DEBUG=1) to see the traceback."""


class CommandParser(OneLineErrorParser):
    """The ``pe-rlhf`` parser: one-line errors (:class:`~pe_rlhf.errors.OneLineErrorParser`)."""


def _add_debug_flag(parser: argparse.ArgumentParser, top: bool = True) -> None:
    """``--debug`` on ``parser`` and, so that it may follow the command too, on every subparser below it."""
    parser.add_argument("--debug", action="store_true", default=False if top else argparse.SUPPRESS,
                        help="on an error, show the traceback instead of one 'error:' line")
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases share a parser
                _add_debug_flag(sub, top=False)


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with one subparser per entry of :data:`SUBCOMMANDS`."""
    parser = CommandParser(prog="pe-rlhf", description=DESCRIPTION, epilog=EPILOG,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in SUBCOMMANDS.values():
        add(subparsers)
    _add_debug_flag(parser)
    return parser


def _is_config_error(error: BaseException) -> bool:
    # A ConfigError exists only once its module is imported; importing it here would cost seconds.
    config = sys.modules.get("pe_rlhf.runtime.config_rules")
    return config is not None and isinstance(error, config.ConfigError)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: sys.argv[1:]) and run the chosen subcommand; returns its exit code. A bad
    argument or value raises ``SystemExit(2)`` after one ``error:`` line (see the module docstring)."""
    args = build_parser().parse_args(argv)
    debug = args.debug or debug_requested()
    args.subparser.debug = debug
    try:
        return args.handler(args, args.subparser)
    except ValueError as e:  # a ConfigError a subcommand did not turn into parser.error itself
        if debug or not _is_config_error(e):
            raise
        fail(str(e))


if __name__ == "__main__":
    sys.exit(main())
