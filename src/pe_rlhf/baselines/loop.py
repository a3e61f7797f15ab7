"""The baselines' training loop, shared by the online recipes: collect a batch, learn, log, evaluate, checkpoint.

Top to bottom in :meth:`BaselineRun.collect` / :meth:`BaselineRun.iteration`:

0. a learner with a ``pretrain`` hook (HG-DAgger, IWR) fits on its demonstrations first (row at step 0);
1. a TorchRL ``Collector`` runs the learner's stochastic actor on one env (``collector.frames_per_batch``
   steps a batch, the env reward and ``("next", "cost")``), seeded from ``seed``; a learner's ``make_env``
   and ``exploration_type`` replace the plain env and random sampling (HG-DAgger, IWR: the mentor takes
   over, the actor acts deterministically);
2. :class:`~pe_rlhf.baselines.episodes.EpisodeTracker` records the episodes that ended (return, cost,
   success) and the cost window the constrained methods measure ``J_c`` on;
3. the learner's ``learn`` (:mod:`pe_rlhf.baselines.algorithms`) does the method's update(s);
4. one ``metrics.csv`` row: ``env_steps``, ``wall_time``, ``train/*`` (episode return and cost, totals,
   ``lambda``), ``loss/*``; every ``eval.every_frames`` a deterministic evaluation on ``eval.split``
   (``eval/*``); every ``checkpoint.every_frames`` a checkpoint (:mod:`pe_rlhf.runtime.checkpoint`:
   networks, optimisers, ``lambda``, the replay buffer, RNG states, counters), which ``--resume`` continues.

The run ends with a checkpoint, the final evaluation and ``actor.pt`` (``weights_only`` loadable into
:func:`pe_rlhf.modules.make_actor`). The offline methods (BC, CQL) never collect: :func:`train_baseline`
hands them to :mod:`pe_rlhf.baselines.offline`, which writes the same outputs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType
from tqdm import tqdm

from pe_rlhf.baselines.algorithms import CPOLearner, PPOLearner, SACLearner
from pe_rlhf.baselines.config import algorithm_name, method_of
from pe_rlhf.baselines.episodes import EpisodeTracker, batch_log
from pe_rlhf.envs.torchrl_env import make_env
from pe_rlhf.threads import FreeCores, torch_threads
from pe_rlhf.training.builders import obs_dim
from pe_rlhf.training.config import driving_config
from pe_rlhf.training.trainer import EVAL_KEYS, next_multiple, evaluate_actor

ACTOR_FILE = "actor.pt"


def _buffer(size: int) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=LazyTensorStorage(max(int(size), 1)))


def compact_copy(buffer: TensorDictReplayBuffer) -> TensorDictReplayBuffer:
    """A buffer holding just ``buffer``'s items, oldest first, for a checkpoint: a ``LazyTensorStorage`` dumps
    all its slots, 2 GB for the paper's 1M-transition buffer however little of it is filled. Extending an
    empty buffer with it restores the same items (at the same indices until the buffer has wrapped)."""
    n = len(buffer)
    copy = _buffer(n)
    if n:
        cursor = buffer.write_count % buffer.storage.max_size if n == buffer.storage.max_size else 0
        copy.extend(buffer.storage[(torch.arange(n) + cursor) % n])
    return copy


class BaselineRun:
    """One training run of ``cfg.method``: learner, tracker, counters, and the work done on each batch."""

    def __init__(self, cfg, logger, checkpoint_dir: Path | None, run_dir: Path | None = None):
        self.cfg, self.logger, self.checkpoint_dir = cfg, logger, checkpoint_dir
        self.method = method_of(cfg)
        self.env_config = driving_config(cfg)
        self.started = time.time()
        self.learner = build_learner(cfg, obs_dim(cfg), run_dir)
        self.tracker = EpisodeTracker(int(cfg.constraint.window) if "constraint" in cfg else 10)
        self.frames, self.iterations, self.saved_step = 0, 0, -1
        self.seconds = {"env": 0.0, "update": 0.0, "eval": 0.0, "earlier_sessions": 0.0}
        self.free_cores = FreeCores(torch.get_num_threads())  # the updates' threads: what other processes leave

    @property
    def total_frames(self) -> int:
        return int(self.cfg.collector.total_frames)

    # -- checkpoints --------------------------------------------------------------------------
    def save(self) -> Path:
        from pe_rlhf.runtime.checkpoint import save_checkpoint

        buffers = {name: compact_copy(b) for name, b in self.learner.replay_buffers.items()}
        seconds = dict(self.seconds, earlier_sessions=self.wall_time())
        state = {"tracker": self.tracker.state_dict(), "iterations": self.iterations, "seconds": seconds,
                 "env_config": self.env_config.to_dict(), "buffer_lengths": {k: len(b) for k, b in buffers.items()}}
        path = save_checkpoint(self.checkpoint_dir, step=self.frames, keep=int(self.cfg.checkpoint.keep),
                               modules=self.learner.modules, optimizers=self.learner.optimizers,
                               replay_buffers=buffers, state=state)
        self.saved_step = self.frames
        return path

    def resume(self) -> None:
        """Load the newest checkpoint; the episode in progress when it was written is lost (a new one starts)."""
        from pe_rlhf.runtime.checkpoint import STATE, find_checkpoint, load_checkpoint

        ckpt = find_checkpoint(self.checkpoint_dir)
        if ckpt is None:
            raise FileNotFoundError(f"no complete checkpoint under {self.checkpoint_dir}")
        lengths = json.loads((ckpt / STATE).read_text()).get("buffer_lengths", {})
        holders = {name: _buffer(lengths.get(name, 1)) for name in self.learner.replay_buffers}
        state = load_checkpoint(ckpt, modules=self.learner.modules, optimizers=self.learner.optimizers,
                                replay_buffers=holders)
        if state.get("env_config") != self.env_config.to_dict():
            raise ValueError(f"cannot resume from {ckpt}: it was trained under env {state.get('env_config')}, the "
                             f"config now says {self.env_config.to_dict()}")
        for name, holder in holders.items():
            if len(holder):
                self.learner.replay_buffers[name].extend(holder.storage[:len(holder)])
        self.frames = self.saved_step = int(state["step"])
        self.iterations = int(state["iterations"])
        self.tracker.load_state_dict(state["tracker"])
        self.tracker.reset_running()
        self.seconds = {k: float(v) for k, v in state["seconds"].items()}
        self.logger.truncate_after(self.frames + 1)  # rows after the checkpoint are logged again

    # -- the loop ------------------------------------------------------------------------------
    def wall_time(self) -> float:
        return self.seconds["earlier_sessions"] + time.time() - self.started

    def pretrain(self) -> None:
        """A learner with a ``pretrain`` hook (HG-DAgger, IWR: BC on the demonstrations) runs it before the first
        batch of a fresh run; its columns make the row at step 0."""
        if self.frames > 0 or not hasattr(self.learner, "pretrain"):
            return
        t_update = time.time()
        with torch_threads(self.free_cores()):
            log = self.learner.pretrain()
        self.seconds["update"] += time.time() - t_update
        self.logger.log(0, {**log, "env_steps": 0, "wall_time": self.wall_time()})

    def collect(self) -> None:
        remaining = self.total_frames - self.frames
        if remaining <= 0:
            return
        fpb = int(self.cfg.collector.frames_per_batch)
        # Learner hooks: the imitation learners collect with the mentor in the loop, deterministically.
        env = self.learner.make_env(self.env_config) if hasattr(self.learner, "make_env") else make_env(self.env_config)
        env.set_seed(int(self.cfg.seed) + self.frames)  # a resumed run draws other scenes than its start did
        collector = Collector(env, self.learner.actor, frames_per_batch=fpb, total_frames=-(-remaining // fpb) * fpb,
                              exploration_type=getattr(self.learner, "exploration_type", ExplorationType.RANDOM),
                              auto_register_policy_transforms=False, **self.learner.collector_kwargs(self.frames))
        self.next_eval = next_multiple(self.frames, int(self.cfg.eval.every_frames))
        self.next_ckpt = next_multiple(self.frames, int(self.cfg.checkpoint.every_frames))
        self.bar = tqdm(total=self.total_frames, initial=self.frames, desc=self.method.name, unit="step")
        try:
            with torch_threads(1):  # acting: tiny matmuls, faster on one thread (pe_rlhf.threads)
                t_env = time.time()
                for batch in collector:
                    self.seconds["env"] += time.time() - t_env
                    self.iteration(batch)
                    if self.frames >= self.total_frames:
                        break
                    t_env = time.time()
        except FloatingPointError as e:  # a non-finite loss, gradient or parameter: keep what was learned
            if self.checkpoint_dir is None:
                raise
            raise FloatingPointError(f"{e}. Saved checkpoint {self.save()} (frame {self.frames})") from e
        finally:
            self.bar.close()
            collector.shutdown()

    def iteration(self, batch) -> None:
        cfg = self.cfg
        episodes = self.tracker.add(batch)
        self.frames += episodes.steps
        self.iterations += 1
        t_update = time.time()
        with torch_threads(self.free_cores()):
            log = self.learner.learn(batch, self.frames, self.tracker)
        self.seconds["update"] += time.time() - t_update
        log.update(batch_log(self.tracker, episodes))
        if self.frames >= self.next_eval:
            self.next_eval = next_multiple(self.frames, int(cfg.eval.every_frames))
            log.update(self.evaluate_columns())
        log.update({"env_steps": self.frames, "wall_time": self.wall_time(),
                    **{f"time/{k}_seconds": v for k, v in self.seconds.items() if k != "earlier_sessions"}})
        last = self.frames >= self.total_frames
        if last or self.iterations % int(cfg.logger.log_every) == 0 or any(k.startswith("eval/") for k in log):
            self.logger.log(self.frames, log)
        self.bar.update(episodes.steps)
        postfix = {"ret": log.get("train/episode_return"), "viol": int(self.tracker.safety_violations),
                   "succ": round(self.tracker.success_rate, 2), "lam": log.get("train/lambda"),
                   "takeover": log.get("train/takeover_rate")}
        self.bar.set_postfix({k: (round(v, 2) if isinstance(v, float) else v) for k, v in postfix.items()
                              if v is not None}, refresh=False)
        if self.checkpoint_dir is not None and self.frames >= self.next_ckpt:
            self.next_ckpt = next_multiple(self.frames, int(cfg.checkpoint.every_frames))
            self.save()

    def evaluate(self, episodes: int) -> dict:
        t = time.time()
        summary = evaluate_actor(self.learner.actor, self.cfg, self.env_config, episodes)
        self.seconds["eval"] += time.time() - t
        return summary

    def evaluate_columns(self) -> dict[str, float]:
        summary = self.evaluate(int(self.cfg.eval.episodes))
        return {f"eval/{k}_{s}": summary[k][s] for k in EVAL_KEYS for s in ("mean", "std")}

    def finish(self, out_dir: Path) -> dict:
        """A last checkpoint, the final evaluation on ``eval.split`` (with training totals) and ``actor.pt``."""
        if self.checkpoint_dir is not None and self.frames > self.saved_step:
            self.save()
        with torch_threads(1):
            final = self.evaluate(int(self.cfg.eval.episodes))
        t = self.tracker
        final["method"] = self.method.name
        final["algorithm"] = algorithm_name(str(self.cfg.method))
        final["training"] = {"env_steps": self.frames, "episodes": t.episodes, "safety_violations": t.safety_violations,
                             "success_rate": t.success_rate, "sim_errors": t.sim_errors,
                             "wall_time_s": self.wall_time(), **{f"{k}_s": v for k, v in self.seconds.items()}}
        if hasattr(self.learner, "training_totals"):  # the imitation learners' mentor data and takeovers
            final["training"].update(self.learner.training_totals())
        torch.save(self.learner.actor.state_dict(), Path(out_dir) / ACTOR_FILE)
        return final


def build_learner(cfg, obs_dim: int, run_dir=None):
    """The learner of ``cfg.method`` (``run_dir``: where the imitation learners record missing demonstrations
    when ``data.path`` is null; the offline methods have their own run, :mod:`pe_rlhf.baselines.offline`)."""
    m = method_of(cfg)
    if m.family in ("gail", "hil"):
        from pe_rlhf.baselines.imitation_learners import (
            GAILLearner,
            InterventionLearner,
        )

        if m.family == "gail":
            return GAILLearner(cfg, obs_dim, run_dir)
        return InterventionLearner(cfg, obs_dim, run_dir, weighted=str(cfg.method) == "iwr")
    if m.family == "sac":
        return SACLearner(cfg, obs_dim, m.lagrangian)
    if m.family == "ppo":
        return PPOLearner(cfg, obs_dim, m.lagrangian)
    return CPOLearner(cfg, obs_dim)


def load_baseline_actor(run_dir: str | Path):
    """The trained actor of a finished baseline run: ``config.yaml`` for the sizes, ``actor.pt`` loaded
    with ``weights_only=True`` into :func:`pe_rlhf.modules.make_actor` (evaluate it with
    :class:`pe_rlhf.evaluation.TorchRLPolicyAdapter`)."""
    from pe_rlhf.training.trained_policy import load_run_actor

    return load_run_actor(run_dir)


def train_baseline(cfg, out_dir: Path, logger, checkpoint_dir: Path | None = None, resume: bool = False) -> dict:
    """Train ``cfg.method`` (a validated baseline config); returns the final evaluation summary dict."""
    if method_of(cfg).family == "offline":
        from pe_rlhf.baselines.offline import train_offline

        return train_offline(cfg, out_dir, logger, checkpoint_dir, resume)
    torch.manual_seed(int(cfg.seed))
    run = BaselineRun(cfg, logger, checkpoint_dir, Path(out_dir))
    if resume:
        run.resume()
    run.pretrain()
    run.collect()
    return run.finish(out_dir)
