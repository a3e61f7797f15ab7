"""The baselines' command line: what ``recipes/<method>/train.py`` runs (``main("sac_lag")``).

    python recipes/<method>/train.py [profile=paper|cpu|smoke] [group.key=value ...] [--out DIR]
    python recipes/<method>/train.py --resume DIR [group.key=value ...]   # continue from its last checkpoint

Outputs in the run folder: ``config.yaml`` (the resolved config), ``metrics.csv``, ``final_eval.json``
(the six metrics on ``eval.split`` with deterministic actions, plus training totals),
``learning_curves.png`` (+ ``testing_curves.png`` with periodic evaluations), ``actor.pt`` and
``checkpoints/``; the imitation methods also ``demos/`` when ``data.path`` is null (the recorded
demonstrations).

A bad config value or argument: one line ``error: <message>`` on stderr and exit code 2 when the script
runs (``train.py`` calls :func:`~pe_rlhf.training.recipe.run_command_line`); ``PE_RLHF_DEBUG=1`` shows
the traceback. Called as a function, ``main(method, argv)`` raises the ConfigError.
"""

from __future__ import annotations

import time
from pathlib import Path

from pe_rlhf.baselines.config import METHODS, algorithm_name, load_baseline_config
from pe_rlhf.baselines.loop import train_baseline
from pe_rlhf.baselines.plots import plot_baseline_curves
from pe_rlhf.evaluation import write_json
from pe_rlhf.training.config import save_config, to_container
from pe_rlhf.training.metrics_logger import CSV_NAME, MetricsLogger
from pe_rlhf.training.recipe import RecipeArgumentParser, report_final

FINAL_EVAL = "final_eval.json"


def run_dir(cfg, method: str, out: str | None) -> Path:
    return Path(out or cfg.logger.out_dir or f"runs/{method}-{time.strftime('%Y%m%d-%H%M%S')}")


def main(method: str, argv: list[str] | None = None) -> dict:
    """Parse ``argv``, train ``method``, write the run folder; returns the final evaluation dict."""
    name = METHODS[method].name
    parser = RecipeArgumentParser(prog=f"recipes/{method}/train.py",
                                  description=f"{name} baseline ({__doc__.splitlines()[0]})")
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. profile=cpu optim.lr=3e-4")
    parser.add_argument("--out", default=None, help=f"output folder (default runs/{method}-<time>)")
    parser.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR")
    parser.add_argument("--compare", default=None, metavar="POLICY",
                        help="also evaluate a registered policy (e.g. idm-mobil) on the same test scenes")
    args = parser.parse_args(argv)
    from pe_rlhf.training.trainer import registered_policies

    if args.compare and args.compare not in registered_policies():  # fail now, not after training
        parser.error(f"--compare {args.compare!r}: allowed: {sorted(registered_policies())}")
    if args.resume:
        out = Path(args.resume)
        cfg = load_baseline_config(method, out / "config.yaml", overrides=args.overrides, apply_profile=False)
    else:
        cfg = load_baseline_config(method, overrides=args.overrides)
        out = run_dir(cfg, method, args.out)
        out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml", algorithm_name(method))  # on --resume: with the overrides it continued under
    lg = cfg.logger
    with MetricsLogger(out, csv=bool(lg.csv), wandb=bool(lg.wandb), wandb_mode=str(lg.wandb_mode),
                       wandb_project=str(lg.wandb_project), tensorboard=bool(lg.tensorboard), mlflow=bool(lg.mlflow),
                       config=to_container(cfg), resume=bool(args.resume)) as logger:
        final = train_baseline(cfg, out, logger, checkpoint_dir=out / "checkpoints", resume=bool(args.resume))
    write_json(out / FINAL_EVAL, final)
    if lg.csv:
        plot_baseline_curves(out / CSV_NAME, out, cfg.constraint.cost_limit if "constraint" in cfg else None,
                             steps_are_updates=METHODS[method].family == "offline")
    report_final(out, name, final, args.compare, cfg)
    return final
