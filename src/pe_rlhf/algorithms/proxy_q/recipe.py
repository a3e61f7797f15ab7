"""What the proxy-Q recipes' scripts (``recipes/pe_rlhf``, ``recipes/haco``, ``recipes/haim_drl``, ``recipes/pvp``)
call around their training loop: the config composed and checked, the run folder held, the outputs written, the
summary printed.

The loop itself is the script's (``recipes/pe_rlhf/train.py``'s ``train(cfg, out, logger, resume)``; HACO's,
HAIM-DRL's and PVP's scripts run the same one over their own ``config.yaml``), handed here as ``loop``. A script
calls :func:`hydra_task` from its ``@hydra.main`` function, :func:`run_script` as its ``__main__`` and :func:`main`
as the command line as a function (tests, ``pe-rlhf sweep``: :func:`load_recipe_script`): every recipe's command
line (:mod:`pe_rlhf.runtime.recipe`: the flags ``--out``, ``--compare``, ``--resume``, Hydra's overrides, the
one-line errors), with this family's schema (:data:`~pe_rlhf.algorithms.proxy_q.config_schema.PROXY_Q`), loader
(:func:`load_run_config`: :func:`~pe_rlhf.algorithms.proxy_q.config.load_config`) and finish
(:func:`~pe_rlhf.algorithms.proxy_q.config.finish_config`). The baseline recipes plug theirs into the same command
line (:mod:`pe_rlhf.algorithms.baselines.cli`).

Outputs in the run folder: ``config.yaml`` (resolved, with the method's registry name as ``algorithm:``),
``metrics.csv``, ``checkpoints/``, ``final_eval.json`` (with ``"algorithm"``), ``training_curves.png``,
``actor.safetensors``, ``test_episode.gif`` (with ``eval.video``) and ``reference_<policy>.json`` (with ``--compare``).
"""

from __future__ import annotations

import functools
import importlib.util
import time
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig

from pe_rlhf.evaluation import TorchRLPolicyAdapter, write_json
from pe_rlhf.runtime import recipe
from pe_rlhf.runtime.config import save_config, to_container
from pe_rlhf.runtime.metrics_logger import MetricsLogger
from pe_rlhf.runtime.plots import plot_learning_curves
from pe_rlhf.runtime.recipe import RunOptions, report_final
from pe_rlhf.runtime.buffer_rows import check_buffer_fits
from pe_rlhf.runtime.resume_changes import announce_changes
from pe_rlhf.runtime.run_folder import hold_run_folder
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.algorithms.proxy_q.config import algorithm_name, finish_config, load_config, method_name
from pe_rlhf.algorithms.proxy_q.config_schema import PROXY_Q
from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor
from pe_rlhf.algorithms.proxy_q.trainer import RESUME_REFUSED

# A recipe script's training loop: loop(cfg, out, logger, resume) -> the final evaluation (final_eval.json's dict).
Loop = Callable[[DictConfig, Path, MetricsLogger, bool], dict]


def main(argv: list[str] | None = None, *, loop: Loop, config_path: str | Path | None = None,
         description: str | None = None) -> dict:
    """Run a recipe's ``loop``: ``config_path`` is its ``config.yaml`` (None: ``recipes/pe_rlhf/config.yaml``,
    see :func:`~pe_rlhf.algorithms.proxy_q.config.load_config`); ``argv`` as on the command line (Hydra's flags
    aside)."""
    return recipe.main(argv, description=description, load=functools.partial(load_run_config, config_path=config_path),
                       train=functools.partial(run, loop=loop))


def run_script(task: Callable[[], object], config_path: str | Path, loop: Loop) -> None:
    """A recipe script's ``__main__`` (:func:`pe_rlhf.runtime.recipe.run_script` with the proxy-Q schema)."""
    recipe.run_script(task, schema=PROXY_Q, load=functools.partial(load_run_config, config_path=config_path),
                      train=functools.partial(run, loop=loop))


def hydra_task(cfg: DictConfig, loop: Loop) -> dict:
    """The body of a recipe's ``@hydra.main`` function: ``mentor.name=human``'s defaults and every rule
    (:func:`~pe_rlhf.algorithms.proxy_q.config.finish_config`), then :func:`run` with the script's ``loop``."""
    return recipe.hydra_task(cfg, finish=finish_config, train=functools.partial(run, loop=loop))


def load_recipe_script(name: str, recipes_dir: str | Path | None = None):
    """``<recipes_dir>/<name>/train.py`` as a module (its ``main(argv)`` runs the recipe); ``recipes_dir`` None: the
    folder the configs are read from (:func:`~pe_rlhf.algorithms.proxy_q.config.default_config_path`)."""
    from pe_rlhf.algorithms.proxy_q.config import default_config_path

    if recipes_dir is None:
        config = default_config_path()
        if config is None:
            raise FileNotFoundError("the recipes folder (recipes/<name>/train.py) is not found: run from a source "
                                    "checkout or set $PE_RLHF_RECIPES")
        recipes_dir = config.parent.parent
    path = Path(recipes_dir) / name / "train.py"
    spec = importlib.util.spec_from_file_location("train", path)  # the name Hydra's --help shows, as when run
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_run_config(options: RunOptions, overrides: list[str], config_path: str | Path | None) -> DictConfig:
    """The run's config: with ``--resume``, the run folder's ``config.yaml`` (composed over the schema, without its
    profile) and ``overrides``; else the recipe's ``config.yaml`` composed with them."""
    if options.resume:
        return load_config(Path(options.resume) / "config.yaml", overrides=overrides, apply_profile=False)
    return load_config(config_path, overrides=overrides)


def run(cfg: DictConfig, options: RunOptions = RunOptions(), *, loop: Loop) -> dict:
    """Train a validated ``cfg`` with the script's ``loop`` into ``options.out`` (or continue the run in
    ``options.resume``), write the outputs, print the final table."""
    method = method_name(cfg)
    out = Path(options.resume) if options.resume else \
        Path(options.out or f"runs/{method.lower()}-{time.strftime('%Y%m%d-%H%M%S')}")
    rb = cfg.replay_buffer  # refused before anything is written: replay (2 storages when balanced) and warm-up
    check_buffer_fits("replay_buffer.size", int(rb.size), 8 * obs_dim(cfg) + 256,
                      3 if rb.get("takeover_share") is not None else 2, saved_rows=int(cfg.collector.total_frames),
                      checkpoints=int(cfg.checkpoint.keep) + 1, folder=out)
    with hold_run_folder(out):  # one writer per run folder, for the run's whole life
        return _run_in(out, cfg, options, method, loop)


def _run_in(out: Path, cfg: DictConfig, options: RunOptions, method: str, loop: Loop) -> dict:
    if options.resume:  # each changed setting applied (and said) or refused in one line; config.yaml follows
        announce_changes(load_config(out / "config.yaml", apply_profile=False), cfg, RESUME_REFUSED, str(out))
    save_config(cfg, out / "config.yaml", algorithm_name(cfg))
    resume = bool(options.resume)
    with MetricsLogger(out, backends=cfg.logger.backends, project=str(cfg.logger.project), config=to_container(cfg),
                       resume=resume) as logger:
        final = loop(cfg, out, logger, resume)
    write_json(out / "final_eval.json", final)
    plot_learning_curves(out / "metrics.csv", out, warmup_steps=int(cfg.collector.warmup_steps))
    report_final(out, method, final, cfg, options, policy=lambda: TorchRLPolicyAdapter(load_run_actor(out)))
    return final
