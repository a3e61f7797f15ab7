"""PE-RLHF training recipe (HACO with ``selector.enabled=false physics.enabled=false``).

    python recipes/pe_rlhf/train.py [profile=cpu|smoke|paper] [group.key=value ...] [--out DIR]
    python recipes/pe_rlhf/train.py --resume DIR      # continue a killed run from its last checkpoint

Everything reusable lives in ``pe_rlhf.training``; this script only wires config, outputs and the loop.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from pe_rlhf.evaluation import print_summary, write_json
from pe_rlhf.training.config import load_config, method_name, save_config, to_container
from pe_rlhf.training.metrics_logger import MetricsLogger
from pe_rlhf.training.plots import plot_learning_curves
from pe_rlhf.training.trainer import evaluate_reference, registered_policies, train


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
        cfg = load_config(overrides=args.overrides)
    method = method_name(cfg)
    if not args.resume:
        out = Path(args.out or cfg.logger.out_dir or f"runs/{method.lower()}-{time.strftime('%Y%m%d-%H%M%S')}")
        out.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out / "config.yaml")
    with MetricsLogger(out, csv=bool(cfg.logger.csv), wandb=bool(cfg.logger.wandb), wandb_mode=str(cfg.logger.wandb_mode),
                       wandb_project=str(cfg.logger.wandb_project), tensorboard=bool(cfg.logger.tensorboard),
                       config=to_container(cfg), resume=bool(args.resume)) as logger:
        final = train(cfg, out, logger, checkpoint_dir=out / "checkpoints", resume=bool(args.resume))
    write_json(out / "final_eval.json", final)
    plot_learning_curves(out / "metrics.csv", out)
    rows = [(method, final)]
    if args.compare:
        reference = evaluate_reference(args.compare, cfg)
        write_json(out / f"reference_{args.compare}.json", reference)
        rows.insert(0, (args.compare, reference))
    print_summary(rows)
    print(f"outputs in {out}")
    return final


if __name__ == "__main__":
    main()
