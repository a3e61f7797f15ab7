"""The baselines' command line: what ``recipes/<method>/train.py`` runs.

    python recipes/<method>/train.py [profile=paper|cpu|smoke] [group.key=value ...] [--out DIR] [--compare POLICY]
    python recipes/<method>/train.py --resume DIR [group.key=value ...]   # continue from its last checkpoint
    python recipes/<method>/train.py profile=smoke --cfg job              # print the composed config, run nothing

A recipe's ``train.py`` is every recipe's layout (:mod:`pe_rlhf.runtime.recipe`): a ``@hydra.main``
function over its ``config.yaml`` (a Hydra config over the method's structured config,
:mod:`pe_rlhf.algorithms.baselines.config`) that hands the composed config to :func:`hydra_task`, run through
:func:`run_script`; the same flags beside Hydra's ``key=value`` overrides and the same ``--cfg job``; Hydra neither
changes the working directory nor writes an output folder. ``main(method, argv)`` is the command line as a
function (tests, ``pe-rlhf sweep``), over ``recipes/<method>/config.yaml``.

Outputs in the run folder: ``config.yaml`` (the resolved config), ``metrics.csv``, ``final_eval.json``
(the six metrics on ``eval.split`` with deterministic actions, plus training totals),
``learning_curves.png`` (+ ``testing_curves.png`` with periodic evaluations), ``actor.safetensors`` and
``checkpoints/``; the imitation methods also ``demos/`` when ``data.path`` is null (the recorded
demonstrations).

A bad config value or argument: one line ``error: <message>`` on stderr and exit code 2 when the script
runs; ``PE_RLHF_DEBUG=1`` shows the traceback. Called as a function, ``main(method, argv)`` raises the ConfigError.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig

from pe_rlhf.algorithms.baselines.config import (
    METHODS,
    algorithm_name,
    load_baseline_config,
    recipe_schema,
    validate_baseline_config,
)
from pe_rlhf.algorithms.baselines.loop import train_baseline
from pe_rlhf.algorithms.baselines.plots import plot_baseline_curves
from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor
from pe_rlhf.evaluation import TorchRLPolicyAdapter, write_json
from pe_rlhf.runtime import recipe
from pe_rlhf.runtime.config import save_config, to_container
from pe_rlhf.runtime.metrics_logger import CSV_NAME, MetricsLogger
from pe_rlhf.runtime.recipe import RunOptions, report_final
from pe_rlhf.runtime.run_folder import hold_run_folder

FINAL_EVAL = "final_eval.json"


def run_dir(method: str, out: str | None) -> Path:
    """The run folder: ``--out DIR``, else ``runs/<method>-<time>``."""
    return Path(out or f"runs/{method}-{time.strftime('%Y%m%d-%H%M%S')}")


def load_run_config(method: str, options: RunOptions, overrides: list[str],
                    config_path: str | Path | None = None) -> DictConfig:
    """The run's config: with ``--resume``, the run folder's ``config.yaml`` (composed over the schema, without its
    profile) and ``overrides``; else the recipe's ``config.yaml`` (``config_path``, None:
    ``recipes/<method>/config.yaml``) composed with them."""
    if options.resume:
        return load_baseline_config(method, Path(options.resume) / "config.yaml", overrides, apply_profile=False)
    return load_baseline_config(method, config_path, overrides)


def main(method: str, argv: list[str] | None = None, *, config_path: str | Path | None = None) -> dict:
    """Parse ``argv``, train ``method``, write the run folder; returns the final evaluation dict."""
    return recipe.main(argv, description=f"{METHODS[method].name} baseline ({__doc__.splitlines()[0]})",
                       load=functools.partial(load_run_config, method, config_path=config_path),
                       train=functools.partial(run, method))


def run_script(task: Callable[[], object], method: str, config_path: str | Path) -> None:
    """A recipe script's ``__main__`` (:func:`pe_rlhf.runtime.recipe.run_script` with ``method``'s schema)."""
    recipe.run_script(task, schema=recipe_schema(method),
                      load=functools.partial(load_run_config, method, config_path=config_path),
                      train=functools.partial(run, method))


def hydra_task(cfg: DictConfig, method: str) -> dict:
    """The body of a recipe's ``@hydra.main`` function: check the composed ``cfg``, then :func:`run` it."""
    return recipe.hydra_task(cfg, finish=functools.partial(_validated, method=method),
                             train=functools.partial(run, method))


def _validated(cfg: DictConfig, overrides: list[str], method: str) -> DictConfig:
    validate_baseline_config(cfg, method)
    return cfg


def run(method: str, cfg: DictConfig, options: RunOptions = RunOptions()) -> dict:
    """Train ``method`` with a validated ``cfg`` into ``options.out`` (or continue the run in ``options.resume``),
    write the outputs, print the final table."""
    out = Path(options.resume) if options.resume else run_dir(method, options.out)
    with hold_run_folder(out):  # one writer per run folder, for the run's whole life
        return _run_in(out, method, cfg, options)


def _run_in(out: Path, method: str, cfg: DictConfig, options: RunOptions) -> dict:
    name = METHODS[method].name
    save_config(cfg, out / "config.yaml", algorithm_name(method))  # on --resume: with the overrides it continued under
    with MetricsLogger(out, backends=cfg.logger.backends, project=str(cfg.logger.project), config=to_container(cfg),
                       resume=bool(options.resume)) as logger:
        final = train_baseline(cfg, out, logger, checkpoint_dir=out / "checkpoints", resume=bool(options.resume))
    write_json(out / FINAL_EVAL, final)
    plot_baseline_curves(out / CSV_NAME, out, cfg.constraint.cost_limit if "constraint" in cfg else None,
                         steps_are_updates=METHODS[method].family == "offline")
    report_final(out, name, final, cfg, options, policy=lambda: TorchRLPolicyAdapter(load_run_actor(out)))
    return final
