"""The online baselines as one :class:`~pe_rlhf.runtime.run.Learner`: collect a batch, learn.

:class:`BaselineLearner` plugs into :class:`~pe_rlhf.runtime.run.Run` (evaluation and checkpoint cadence,
logging, ``--resume``, finish, shared with every method); its batches and :meth:`BaselineLearner.learn`:

0. a learner with a ``pretrain`` hook (HG-DAgger, IWR) fits on its demonstrations first (row at step 0);
1. a TorchRL ``Collector`` runs the learner's stochastic actor on one env (``collector.frames_per_batch``
   steps a batch, the env reward and ``("next", "cost")``), seeded from ``seed``; a learner's ``make_env``
   and ``exploration_type`` replace the plain env and random sampling (HG-DAgger, IWR: the mentor takes
   over, the actor acts deterministically);
2. :class:`~pe_rlhf.algorithms.baselines.episodes.EpisodeTracker` records the episodes that ended (return, cost,
   success) and the cost window the constrained methods measure ``J_c`` on;
3. the learner's ``learn`` (:mod:`pe_rlhf.algorithms.baselines.algorithms`) does the method's update(s);
4. (the run's) one ``metrics.csv`` row: ``env_steps``, ``wall_time``, ``train/*`` (episode return and cost,
   totals, ``lambda``), ``loss/*``; every ``eval.every_frames`` a deterministic evaluation on ``eval.split``
   (``eval/*``); every ``checkpoint.every_frames`` a checkpoint (:mod:`pe_rlhf.runtime.checkpoint`:
   networks, optimisers, ``lambda``, the replay buffer, RNG states, counters), which ``--resume`` continues.

The run ends with a checkpoint, the final evaluation and ``actor.safetensors`` (loadable into
:func:`pe_rlhf.modules.make_actor`). The offline methods (BC, CQL) never collect: :func:`train_baseline`
hands them to :mod:`pe_rlhf.algorithms.baselines.offline`, whose learner the same run drives.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType

from pe_rlhf.algorithms.baselines.algorithms import CPOLearner, PPOLearner, SACLearner
from pe_rlhf.algorithms.baselines.config import algorithm_name, method_of
from pe_rlhf.algorithms.baselines.episodes import EpisodeTracker, batch_log
from pe_rlhf.envs.torchrl_env import make_env
from pe_rlhf.runtime.checkpoint import STATE
from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.run import Learner, Run
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.threads import FreeCores, torch_threads


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


class BaselineLearner(Learner):
    """An online baseline as a :class:`~pe_rlhf.runtime.run.Learner`: ``cfg.method``'s learner
    (``self.algorithm``), the episode tracker, and the frames collected."""

    timers = ("env", "update")

    def __init__(self, cfg, run_dir: Path | None = None):
        self.cfg, self.method = cfg, method_of(cfg)
        self.name, self.env_config = self.method.name, driving_config(cfg)
        self.algorithm = build_learner(cfg, obs_dim(cfg), run_dir)
        self.actor = self.algorithm.actor
        self.tracker = EpisodeTracker(int(cfg.constraint.window) if "constraint" in cfg else 10)
        self.progress = 0  # frames
        self.free_cores = FreeCores(torch.get_num_threads())  # the updates' threads: what other processes leave

    def checkpoint_objects(self, checkpoint: Path | None = None) -> dict:
        """The replay buffers compacted; to load ``checkpoint``, buffers of the sizes it holds (then extended
        into the learner's in :meth:`load_state_dict`)."""
        if checkpoint is None:
            buffers = {name: compact_copy(b) for name, b in self.algorithm.replay_buffers.items()}
        else:
            lengths = json.loads((checkpoint / STATE).read_text()).get("buffer_lengths", {})
            self.loaded = buffers = {name: _buffer(lengths.get(name, 1)) for name in self.algorithm.replay_buffers}
        return {"modules": self.algorithm.modules, "optimizers": self.algorithm.optimizers, "replay_buffers": buffers}

    def state_dict(self) -> dict:
        return {"tracker": self.tracker.state_dict(),
                "buffer_lengths": {k: len(b) for k, b in self.algorithm.replay_buffers.items()}}

    def load_state_dict(self, state: dict) -> None:
        """The checkpoint's buffers, frames and tracker; the episode in progress then is lost (a new one starts)."""
        for name, loaded in self.loaded.items():
            if len(loaded):
                self.algorithm.replay_buffers[name].extend(loaded.storage[:len(loaded)])
        self.progress = int(state["step"])
        self.tracker.load_state_dict(state["tracker"])
        self.tracker.reset_running()

    def pretrain(self) -> dict[str, float] | None:
        """A learner with a ``pretrain`` hook (HG-DAgger, IWR: BC on the demonstrations) runs it before the first
        batch of a fresh run; its columns make the row at step 0."""
        if not hasattr(self.algorithm, "pretrain"):
            return None
        with torch_threads(self.free_cores()):
            return {**self.algorithm.pretrain(), "env_steps": 0}

    def batches(self):
        remaining = int(self.cfg.collector.total_frames) - self.progress
        if remaining <= 0:
            return
        fpb, algorithm = int(self.cfg.collector.frames_per_batch), self.algorithm
        # Learner hooks: the imitation learners collect with the mentor in the loop, deterministically.
        env = algorithm.make_env(self.env_config) if hasattr(algorithm, "make_env") else make_env(self.env_config)
        env.set_seed(int(self.cfg.seed) + self.progress)  # a resumed run draws other scenes than its start did
        collector = Collector(env, self.actor, frames_per_batch=fpb, total_frames=-(-remaining // fpb) * fpb,
                              exploration_type=getattr(algorithm, "exploration_type", ExplorationType.RANDOM),
                              auto_register_policy_transforms=False, **algorithm.collector_kwargs(self.progress))
        try:
            for batch in collector:
                yield batch
                if self.progress >= int(self.cfg.collector.total_frames):
                    break
        finally:
            collector.shutdown()

    def learn(self, batch) -> dict[str, float]:
        episodes = self.tracker.add(batch)
        self.progress += episodes.steps
        with torch_threads(self.free_cores()):
            log = self.algorithm.learn(batch, self.progress, self.tracker)
        return {**log, **batch_log(self.tracker, episodes), "env_steps": self.progress}

    def postfix(self, row: dict[str, float]) -> dict:
        postfix = {"ret": row.get("train/episode_return"), "viol": int(self.tracker.safety_violations),
                   "succ": round(self.tracker.success_rate, 2), "lam": row.get("train/lambda"),
                   "takeover": row.get("train/takeover_rate")}
        return {k: (round(v, 2) if isinstance(v, float) else v) for k, v in postfix.items() if v is not None}

    def summary(self, out_dir: Path) -> dict:
        """The method, and training totals (the imitation learners': their mentor data and takeovers too)."""
        t = self.tracker
        training = {"env_steps": self.progress, "episodes": t.episodes, "safety_violations": t.safety_violations,
                    "success_rate": t.success_rate, "sim_errors": t.sim_errors,
                    **(self.algorithm.training_totals() if hasattr(self.algorithm, "training_totals") else {})}
        return {"method": self.method.name, "algorithm": algorithm_name(str(self.cfg.method)), "training": training}


def build_learner(cfg, obs_dim: int, run_dir=None):
    """The learner of ``cfg.method`` (``run_dir``: where the imitation learners record missing demonstrations
    when ``data.path`` is null; the offline methods have their own run, :mod:`pe_rlhf.algorithms.baselines.offline`)."""
    m = method_of(cfg)
    if m.family in ("gail", "hil"):
        from pe_rlhf.algorithms.baselines.imitation_learners import (
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
    """The trained actor of a finished baseline run: ``config.yaml`` for the sizes, the actor file loaded
    with ``weights_only=True`` into :func:`pe_rlhf.modules.make_actor` (evaluate it with
    :class:`pe_rlhf.evaluation.TorchRLPolicyAdapter`)."""
    from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor

    return load_run_actor(run_dir)


def train_baseline(cfg, out_dir: Path, logger, checkpoint_dir: Path | None = None, resume: bool = False) -> dict:
    """Train ``cfg.method`` (a validated baseline config); returns the final evaluation summary dict."""
    if method_of(cfg).family == "offline":
        from pe_rlhf.algorithms.baselines.offline import train_offline

        return train_offline(cfg, out_dir, logger, checkpoint_dir, resume)
    torch.manual_seed(int(cfg.seed))
    run = Run(cfg, BaselineLearner(cfg, Path(out_dir)), logger, checkpoint_dir, total=cfg.collector.total_frames,
              eval_every=cfg.eval.every_frames, checkpoint_every=cfg.checkpoint.every_frames)
    with torch_threads(1):  # acting: tiny matmuls, faster on one thread (pe_rlhf.threads); updates take free cores
        return run.train(Path(out_dir), resume)
