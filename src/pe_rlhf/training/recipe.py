"""The entry point shared by the proxy-Q recipes (``recipes/pe_rlhf``, ``recipes/haco``, ``recipes/haim_drl``): parse the
command line, load the recipe's config, train, write the outputs, print the summary.

Outputs in the run folder: ``config.yaml`` (resolved, with the method's registry name as ``algorithm:``),
``metrics.csv``, ``checkpoints/``, ``final_eval.json`` (with ``"algorithm"``), ``training_curves.png``, ``actor.pt``, ``test_episode.gif`` (with ``eval.video``) and
``reference_<policy>.json`` (with ``--compare``).

Errors, for every recipe (the baselines' ``train.py`` too): a script runs its ``main`` through
:func:`run_command_line`, so a bad config value, file or override (a
:class:`~pe_rlhf.training.config.ConfigError`; the config is checked before anything is built) or a bad
argument prints one line ``error: <message>`` to stderr and exits 2, without a traceback.
``PE_RLHF_DEBUG=1 python recipes/<method>/train.py ...`` shows the traceback instead (an environment
variable, not a flag: the command line is the run's config overrides). Called as a function,
``main(argv)`` raises the ConfigError.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

from pe_rlhf.evaluation import print_summary, write_json
from pe_rlhf.errors import OneLineErrorParser, debug_requested, fail
from pe_rlhf.training.config import ConfigError, algorithm_name, load_config, method_name, save_config, to_container
from pe_rlhf.training.metrics_logger import MetricsLogger
from pe_rlhf.training.plots import plot_learning_curves
from pe_rlhf.training.trainer import evaluate_reference, registered_policies, train



class RecipeArgumentParser(OneLineErrorParser):
    """A recipe's parser: one-line errors (:class:`~pe_rlhf.errors.OneLineErrorParser`), the traceback with
    ``$PE_RLHF_DEBUG``."""


def run_command_line(main: Callable[..., object], *args: object) -> None:
    """Run a recipe script's ``main(*args)`` (the command line is ``sys.argv``): a ConfigError becomes one
    ``error:`` line and exit code 2 (:func:`fail`), unless ``$PE_RLHF_DEBUG`` asks for the traceback."""
    try:
        main(*args)
    except ConfigError as e:
        if debug_requested():
            raise
        fail(str(e))


def main(argv: list[str] | None = None, *, config_path: str | Path | None = None,
         description: str | None = None) -> dict:
    """Run a recipe: ``config_path`` is its ``config.yaml`` (None: ``recipes/pe_rlhf/config.yaml``,
    see :func:`~pe_rlhf.training.config.load_config`); ``argv`` as on the command line."""
    parser = RecipeArgumentParser(description=description)
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. profile=cpu optim.lr=3e-4")
    parser.add_argument("--out", default=None, help="output folder (default runs/<method>-<time>)")
    parser.add_argument("--compare", default=None, metavar="POLICY",
                        help="also evaluate a registered policy (e.g. idm-mobil) on the same test scenes and "
                             "print both in the final table")
    parser.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR")
    args = parser.parse_args(argv)
    if args.compare and args.compare not in registered_policies():  # fail now, not after training
        parser.error(f"--compare {args.compare!r}: allowed: {sorted(registered_policies())}")
    if args.resume:
        out = Path(args.resume)
        cfg = load_config(out / "config.yaml", overrides=args.overrides, apply_profile=False)
    else:
        cfg = load_config(config_path, overrides=args.overrides)
    method = method_name(cfg)
    if not args.resume:
        out = Path(args.out or cfg.logger.out_dir or f"runs/{method.lower()}-{time.strftime('%Y%m%d-%H%M%S')}")
        out.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out / "config.yaml", algorithm_name(cfg))
    with MetricsLogger(out, csv=bool(cfg.logger.csv), wandb=bool(cfg.logger.wandb), wandb_mode=str(cfg.logger.wandb_mode),
                       wandb_project=str(cfg.logger.wandb_project), tensorboard=bool(cfg.logger.tensorboard),
                       mlflow=bool(cfg.logger.mlflow),
                       config=to_container(cfg), resume=bool(args.resume)) as logger:
        final = train(cfg, out, logger, checkpoint_dir=out / "checkpoints", resume=bool(args.resume))
    write_json(out / "final_eval.json", final)
    plot_learning_curves(out / "metrics.csv", out, warmup_steps=int(cfg.collector.warmup_steps))
    report_final(out, method, final, args.compare, cfg)
    return final


def report_final(out: Path, name: str, final: dict, compare: str | None, cfg) -> None:
    """Print the final table (with ``compare``, a reference policy on the same scenes, saved as
    ``reference_<policy>.json``) and where the outputs are; shared by every recipe's entry point."""
    rows = [(name, final)]
    if compare:
        reference = evaluate_reference(compare, cfg)
        write_json(out / f"reference_{compare}.json", reference)
        rows.insert(0, (compare, reference))
    print_summary(rows)
    print(f"outputs in {out}")
