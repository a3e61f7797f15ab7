"""The offline baselines, BC and CQL: gradient steps on recorded demonstrations, no env interaction.

Top to bottom in :meth:`OfflineRun.train`:

1. the demonstrations (:func:`pe_rlhf.baselines.demos.demonstrations`: ``data.path`` or ``<run>/demos``,
   recorded first when missing) fill a TorchRL replay buffer sampling ``optim.batch_size`` transitions;
2. ``optim.updates`` gradient steps of the method's learner (:class:`BCLearner`: TorchRL's ``BCLoss``
   through :class:`~pe_rlhf.baselines.imitation.WeightedBCLoss`; :class:`CQLLearner`: TorchRL's
   ``CQLLoss`` whose actor term is its BC term for the first ``loss.bc_steps`` updates, as RLlib's
   ``bc_iters``), a ``metrics.csv`` row every ``optim.updates_per_iteration`` (``step`` = updates);
3. every ``eval.every_updates`` a deterministic evaluation on ``eval.split``, every
   ``checkpoint.every_updates`` a checkpoint (networks, optimisers, counters, RNG; ``--resume`` continues).

The learner drives no step while training: ``env_steps`` is 0 and ``train/safety_violations_total`` 0;
the demonstrations' own steps and violations (the mentor's, while recording) are ``train/mentor_data_total``
and ``final_eval.json``'s ``training.demo_*``.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import Bounded, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import CQLLoss, SoftUpdate
from tqdm import tqdm

from pe_rlhf.baselines.algorithms import _NoTargets, _params, summarise
from pe_rlhf.baselines.config import algorithm_name, method_of
from pe_rlhf.baselines.demos import DEMO_KEYS, data_totals, demonstrations
from pe_rlhf.baselines.imitation import WeightedBCLoss
from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.threads import torch_threads
from pe_rlhf.training.builders import obs_dim
from pe_rlhf.training.config import driving_config
from pe_rlhf.training.steps import update
from pe_rlhf.training.trainer import EVAL_KEYS, next_multiple, evaluate_actor

ACTOR_FILE = "actor.pt"


class BCLearner:
    """Behaviour cloning of the demonstrations' actions (``loss.function``: nll or mse)."""

    def __init__(self, cfg, obs_dim: int):
        self.cfg = cfg
        self.actor = make_actor(obs_dim, hidden=tuple(cfg.loss.hidden))
        self.loss = WeightedBCLoss(self.actor, str(cfg.loss.function))
        self.optimizers = {"actor": torch.optim.Adam(_params(self.loss.actor_network_params), lr=float(cfg.optim.lr))}
        self.modules = {"loss": self.loss}
        self.targets = _NoTargets()

    def update(self, sample: TensorDictBase) -> dict[str, float]:
        return update(self.loss, self.optimizers, self.targets, sample.select("observation", "action"),
                      self.cfg.optim.max_grad_norm)


class BCThenCQL(nn.Module):
    """``CQLLoss``'s outputs with one actor term: ``loss_actor_bc`` (``alpha log pi(a~|s) - log pi(a_data|s)``)
    for the first ``bc_steps`` calls, ``loss_actor`` after; the other is kept, detached, as a diagnostic
    (``actor`` / ``actor_bc``). The call count is a buffer (checkpointed)."""

    def __init__(self, loss: CQLLoss, bc_steps: int):
        super().__init__()
        self.loss, self.bc_steps = loss, int(bc_steps)
        self.register_buffer("calls", torch.zeros((), dtype=torch.int64))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.loss(tensordict)
        unused = "loss_actor" if int(self.calls) < self.bc_steps else "loss_actor_bc"
        out.set(unused[len("loss_"):], out.pop(unused).detach())
        self.calls += 1
        return out


class CQLLearner:
    """CQL (TorchRL's ``CQLLoss``: twin Q (fixed at 2), target networks, automatic entropy) on the
    demonstrations' reward."""

    def __init__(self, cfg, obs_dim: int):
        lc, lr = cfg.loss, float(cfg.optim.lr)
        self.cfg = cfg
        self.actor = make_actor(obs_dim, hidden=tuple(lc.hidden))
        self.cql = CQLLoss(self.actor, make_qvalue(obs_dim, hidden=tuple(lc.hidden)), loss_function="l2",
                           alpha_init=float(lc.alpha_init),
                           action_spec=Bounded(-1.0, 1.0, (2,)),
                           target_entropy=lc.target_entropy if lc.target_entropy == "auto" else float(lc.target_entropy),
                           temperature=float(lc.temperature), min_q_weight=float(lc.min_q_weight),
                           num_random=int(lc.num_random))
        self.cql.make_value_estimator(gamma=float(lc.gamma))
        self.loss = BCThenCQL(self.cql, int(lc.bc_steps))
        self.soft_update = SoftUpdate(self.cql, tau=float(lc.tau))
        self.optimizers = {"actor": torch.optim.Adam(_params(self.cql.actor_network_params), lr=lr),
                           "qvalue": torch.optim.Adam(_params(self.cql.qvalue_network_params), lr=lr),
                           "alpha": torch.optim.Adam([self.cql.log_alpha], lr=lr)}
        self.modules = {"loss": self.loss}

    def update(self, sample: TensorDictBase) -> dict[str, float]:
        return update(self.loss, self.optimizers, self.soft_update, sample, self.cfg.optim.max_grad_norm)


def build_offline_learner(cfg, obs_dim: int):
    return BCLearner(cfg, obs_dim) if str(cfg.method) == "bc" else CQLLearner(cfg, obs_dim)


class OfflineRun:
    """One offline training run: learner, demonstration buffer, counters, logging (module docstring)."""

    def __init__(self, cfg, logger, checkpoint_dir: Path | None, run_dir: Path | None):
        self.cfg, self.logger, self.checkpoint_dir, self.run_dir = cfg, logger, checkpoint_dir, run_dir
        self.method = method_of(cfg)
        self.env_config = driving_config(cfg)
        self.learner = build_offline_learner(cfg, obs_dim(cfg))
        self.updates, self.iterations, self.saved_step = 0, 0, -1
        self.seconds = {"data": 0.0, "update": 0.0, "eval": 0.0, "earlier_sessions": 0.0}
        self.started = time.time()

    @property
    def total_updates(self) -> int:
        return int(self.cfg.optim.updates)

    def wall_time(self) -> float:
        return self.seconds["earlier_sessions"] + time.time() - self.started

    def load_data(self) -> None:
        t = time.time()
        demos = demonstrations(self.cfg, self.run_dir)
        self.totals = data_totals(demos)
        self.replay = TensorDictReplayBuffer(storage=LazyTensorStorage(demos.numel()),
                                             batch_size=int(self.cfg.optim.batch_size))
        self.replay.extend(demos.select(*DEMO_KEYS))
        self.seconds["data"] += time.time() - t

    # -- checkpoints --------------------------------------------------------------------------
    def save(self) -> Path:
        from pe_rlhf.runtime.checkpoint import save_checkpoint

        state = {"iterations": self.iterations, "seconds": dict(self.seconds, earlier_sessions=self.wall_time()),
                 "env_config": self.env_config.to_dict()}
        path = save_checkpoint(self.checkpoint_dir, step=self.updates, keep=int(self.cfg.checkpoint.keep),
                               modules=self.learner.modules, optimizers=self.learner.optimizers, state=state)
        self.saved_step = self.updates
        return path

    def resume(self) -> None:
        from pe_rlhf.runtime.checkpoint import load_checkpoint

        state = load_checkpoint(self.checkpoint_dir, modules=self.learner.modules, optimizers=self.learner.optimizers)
        if state.get("env_config") != self.env_config.to_dict():
            raise ValueError(f"cannot resume: the checkpoint was trained under env {state.get('env_config')}, the "
                             f"config now says {self.env_config.to_dict()}")
        self.updates = self.saved_step = int(state["step"])
        self.iterations = int(state["iterations"])
        self.seconds = {k: float(v) for k, v in state["seconds"].items()}
        self.started = time.time()
        self.logger.truncate_after(self.updates + 1)

    # -- the loop ------------------------------------------------------------------------------
    def train(self) -> None:
        self.load_data()
        every = int(self.cfg.optim.updates_per_iteration)
        self.next_eval = next_multiple(self.updates, int(self.cfg.eval.every_updates))
        self.next_ckpt = next_multiple(self.updates, int(self.cfg.checkpoint.every_updates))
        bar = tqdm(total=self.total_updates, initial=self.updates, desc=self.method.name, unit="update")
        try:
            while self.updates < self.total_updates:
                n = min(every, self.total_updates - self.updates)
                t = time.time()
                log = summarise([self.learner.update(self.replay.sample()) for _ in range(n)])
                self.seconds["update"] += time.time() - t
                self.updates += n
                self.iterations += 1
                self.log_iteration(log)
                bar.update(n)
                bar.set_postfix({k.split("/", 1)[1]: round(v, 3) for k, v in log.items() if k.startswith("loss/")},
                                refresh=False)
        except FloatingPointError as e:
            if self.checkpoint_dir is None:
                raise
            raise FloatingPointError(f"{e}. Saved checkpoint {self.save()} (update {self.updates})") from e
        finally:
            bar.close()

    def log_iteration(self, log: dict[str, float]) -> None:
        cfg = self.cfg
        if self.updates >= self.next_eval:
            self.next_eval = next_multiple(self.updates, int(cfg.eval.every_updates))
            summary = self.evaluate(int(cfg.eval.episodes))
            log.update({f"eval/{k}_{s}": summary[k][s] for k in EVAL_KEYS for s in ("mean", "std")})
        log.update({"env_steps": 0, "updates": self.updates, "wall_time": self.wall_time(),
                    "train/safety_violations_total": 0.0, "train/mentor_data_total": self.totals["demo_steps"],
                    "train/mentor_data_share": 1.0,
                    **{f"time/{k}_seconds": v for k, v in self.seconds.items() if k != "earlier_sessions"}})
        last = self.updates >= self.total_updates
        if last or self.iterations % int(cfg.logger.log_every) == 0 or any(k.startswith("eval/") for k in log):
            self.logger.log(self.updates, log)
        if self.checkpoint_dir is not None and self.updates >= self.next_ckpt:
            self.next_ckpt = next_multiple(self.updates, int(cfg.checkpoint.every_updates))
            self.save()

    def evaluate(self, episodes: int) -> dict:
        t = time.time()
        with torch_threads(1):
            summary = evaluate_actor(self.learner.actor, self.cfg, self.env_config, episodes)
        self.seconds["eval"] += time.time() - t
        return summary

    def finish(self, out_dir: Path) -> dict:
        if self.checkpoint_dir is not None and self.updates > self.saved_step:
            self.save()
        final = self.evaluate(int(self.cfg.eval.episodes))
        final["method"] = self.method.name
        final["algorithm"] = algorithm_name(str(self.cfg.method))
        final["training"] = {"env_steps": 0, "updates": self.updates, "episodes": 0, "safety_violations": 0.0,
                             **self.totals, "mentor_data_total": self.totals["demo_steps"],
                             "mentor_data_share": 1.0, "wall_time_s": self.wall_time(),
                             **{f"{k}_s": v for k, v in self.seconds.items()}}
        torch.save(self.learner.actor.state_dict(), Path(out_dir) / ACTOR_FILE)
        return final


def train_offline(cfg, out_dir: Path, logger, checkpoint_dir: Path | None = None, resume: bool = False) -> dict:
    """Train ``cfg.method`` (bc or cql) on its demonstrations; returns the final evaluation summary dict."""
    torch.manual_seed(int(cfg.seed))
    run = OfflineRun(cfg, logger, checkpoint_dir, Path(out_dir))
    if resume:
        run.resume()
    run.train()
    return run.finish(out_dir)


__all__ = ["BCLearner", "BCThenCQL", "CQLLearner", "OfflineRun", "train_offline"]
