"""PE-RLHF training recipe: the loop, top to bottom (HACO, HAIM-DRL and PVP run it over their own config.yaml).

    python recipes/pe_rlhf/train.py [profile=cpu|smoke|quick|paper] [group.key=value ...] [--out DIR]
    python recipes/pe_rlhf/train.py --resume DIR      # continue a killed run from its last checkpoint
    python recipes/pe_rlhf/train.py profile=smoke --cfg job   # print the composed config, run nothing

TorchRL's layout: ``config.yaml`` beside this script shows every setting with its value (a Hydra config over the
structured config :class:`~pe_rlhf.algorithms.proxy_q.config_schema.RecipeConfig`); :func:`train` is the loop;
the objects it drives are built by :class:`~pe_rlhf.algorithms.proxy_q.trainer.ProxyQLearner` (the env with the
intervention transform: mentor, physics, selector; the actor, the loss, the optimisers, the buffers, the updater,
the journal) and the cadence every method shares (evaluations, checkpoints, ``--resume``, the final evaluation) is
:class:`~pe_rlhf.runtime.run.Run`'s. A bad value prints one line ``error: ...`` and exits 2; ``--debug`` (or
``PE_RLHF_DEBUG=1``) shows the traceback.

A step of training: ``learner.store`` journals the collected batch, counts it and puts it in the replay buffer
(the warm-up's relabelled as takeovers, the value source fitted once the warm-up ends);
``learner.updater.notify_frames`` runs the updates these frames pay for
(:func:`pe_rlhf.runtime.update.update` on a replay sample: the loss's ``forward``, the optimisers' steps, the
target networks' update); ``run.after_batch`` evaluates, logs and checkpoints when due.
"""

from __future__ import annotations

from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from pe_rlhf.algorithms.proxy_q import recipe
from pe_rlhf.algorithms.proxy_q.trainer import ProxyQLearner
from pe_rlhf.runtime.run import Run
from pe_rlhf.threads import torch_threads

CONFIG = Path(__file__).with_name("config.yaml")


def train(cfg: DictConfig, out: Path, logger, resume: bool = False) -> dict:
    """Train ``cfg`` in the run folder ``out`` (with ``resume``, from its newest checkpoint or journal); ``logger``
    has ``log(step, metrics)``. Returns the final evaluation (``final_eval.json``)."""
    torch.manual_seed(int(cfg.seed))
    update_threads = torch.get_num_threads()  # the updates' threads; acting and evaluation use one
    with torch_threads(1):
        learner = ProxyQLearner(cfg, logger, out / "checkpoints", update_threads)
        run = Run(cfg, learner, logger, out / "checkpoints", total=cfg.collector.total_frames,
                  eval_every=cfg.eval.every_frames, checkpoint_every=cfg.checkpoint.every_frames)
        run.begin(out, resume)
        batches = learner.batches()  # the killed run's journaled batches first, then the collector's
        with run.batches_closed(batches):
            for item in batches:
                before = run.progress
                counts = learner.store(item)  # journal, counters, replay buffer, value-source fit
                if learner.learning:
                    learner.updater.notify_frames(int(counts["steps"]))  # the updates these frames pay for
                run.after_batch(learner.row(counts), before)  # evaluate, log, checkpoint when due
        return run.finish(out)


def main(argv: list[str] | None = None, config: Path = CONFIG) -> dict:
    """The command line as a function (tests, ``pe-rlhf sweep``): ``main(["profile=smoke", "--out", "runs/x"])``;
    ``config``: the recipe's ``config.yaml`` (HACO's, HAIM-DRL's and PVP's scripts pass theirs)."""
    return recipe.main(argv, loop=train, config_path=config, description=__doc__.splitlines()[0])


def run_as_script(config: Path = CONFIG) -> None:
    """The script's ``__main__`` over ``config``: Hydra's command line (``key=value``, ``--cfg job``, ``--help``) and
    the recipe's flags (``--out``, ``--resume``, ``--compare``, ``--debug``)."""

    @hydra.main(config_path=str(config.parent), config_name=config.stem, version_base=None)
    def hydra_main(cfg: DictConfig) -> dict:
        return recipe.hydra_task(cfg, train)

    recipe.run_script(hydra_main, config, train)


if __name__ == "__main__":
    run_as_script()
