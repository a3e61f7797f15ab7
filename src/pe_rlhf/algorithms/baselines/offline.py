"""The offline baselines, BC and CQL: gradient steps on recorded demonstrations, no env interaction.

:class:`OfflineLearner` plugs into :class:`~pe_rlhf.runtime.run.Run`, the loop of every method, its progress
counted in updates (the cadence, checkpoints, ``--resume`` and finish are the run's). Top to bottom:

1. the demonstrations (:func:`pe_rlhf.algorithms.baselines.demos.demonstrations`: ``data.path`` or ``<run>/demos``,
   recorded first when missing) fill a TorchRL replay buffer sampling ``optim.batch_size`` transitions;
2. ``optim.updates`` gradient steps of the method's learner (:class:`BCLearner`: TorchRL's ``BCLoss``
   through :class:`~pe_rlhf.algorithms.baselines.imitation.WeightedBCLoss`; :class:`CQLLearner`: TorchRL's
   ``CQLLoss`` whose actor term is its BC term for the first ``loss.bc_steps`` updates, as RLlib's
   ``bc_iters``), a ``metrics.csv`` row every ``optim.updates_per_iteration`` (``step`` = updates);
3. every ``eval.every_updates`` a deterministic evaluation on ``eval.split``, every
   ``checkpoint.every_updates`` a checkpoint (networks, optimisers, counters, RNG; ``--resume`` continues).

The learner drives no step while training: ``env_steps`` is 0 and ``train/safety_violations_total`` 0;
the demonstrations' own steps and violations (the mentor's, while recording) are ``train/mentor_data_total``
and ``final_eval.json``'s ``training.demo_*``.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import Bounded, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import CQLLoss

from pe_rlhf.algorithms.baselines.algorithms import _NoTargets, _params, summarise
from pe_rlhf.algorithms.baselines.config import algorithm_name, method_of
from pe_rlhf.algorithms.baselines.demos import DEMO_KEYS, data_totals, demonstrations
from pe_rlhf.algorithms.baselines.imitation import WeightedBCLoss
from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import ForeachSoftUpdate, make_adam
from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.run import Learner, Run
from pe_rlhf.runtime.update import update
from pe_rlhf.runtime.world import obs_dim


class BCLearner:
    """Behaviour cloning of the demonstrations' actions (``loss.function``: nll or mse)."""

    def __init__(self, cfg, obs_dim: int):
        self.cfg = cfg
        self.actor = make_actor(obs_dim, hidden=tuple(cfg.loss.hidden))
        self.loss = WeightedBCLoss(self.actor, str(cfg.loss.function))
        self.optimizers = {"actor": make_adam(_params(self.loss.actor_network_params), lr=float(cfg.optim.lr))}
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
        target_entropy = lc.target_entropy if lc.target_entropy == "auto" else float(lc.target_entropy)
        self.cql = CQLLoss(self.actor, make_qvalue(obs_dim, hidden=tuple(lc.hidden)), loss_function="l2",
                           alpha_init=float(lc.alpha_init),
                           action_spec=Bounded(-1.0, 1.0, (2,)),
                           target_entropy=target_entropy,
                           temperature=float(lc.temperature), min_q_weight=float(lc.min_q_weight),
                           num_random=int(lc.num_random))
        self.cql.make_value_estimator(gamma=float(lc.gamma))
        self.loss = BCThenCQL(self.cql, int(lc.bc_steps))
        self.soft_update = ForeachSoftUpdate(self.cql, tau=float(lc.tau))
        self.optimizers = {"actor": make_adam(_params(self.cql.actor_network_params), lr=lr),
                           "qvalue": make_adam(_params(self.cql.qvalue_network_params), lr=lr),
                           "alpha": make_adam([self.cql.log_alpha], lr=lr)}
        self.modules = {"loss": self.loss}

    def update(self, sample: TensorDictBase) -> dict[str, float]:
        return update(self.loss, self.optimizers, self.soft_update, sample, self.cfg.optim.max_grad_norm)


class OfflineLearner(Learner):
    """BC or CQL on demonstrations as a :class:`~pe_rlhf.runtime.run.Learner`: its progress is updates, each
    batch a round of ``optim.updates_per_iteration`` of them (module docstring)."""

    unit, timers = "update", ("data", "update")

    def __init__(self, cfg, run_dir: Path | None):
        self.cfg, self.run_dir, self.method = cfg, run_dir, method_of(cfg)
        self.name, self.env_config = self.method.name, driving_config(cfg)
        self.algorithm = BCLearner(cfg, obs_dim(cfg)) if str(cfg.method) == "bc" else CQLLearner(cfg, obs_dim(cfg))
        self.actor = self.algorithm.actor
        self.progress = 0  # updates

    def checkpoint_objects(self, checkpoint: Path | None = None) -> dict:
        return {"modules": self.algorithm.modules, "optimizers": self.algorithm.optimizers}

    def load_state_dict(self, state: dict) -> None:
        self.progress = int(state["step"])

    def batches(self):
        """The demonstrations into a replay buffer (the run times it as ``data``), then rounds of updates."""
        demos = demonstrations(self.cfg, self.run_dir)
        self.totals = data_totals(demos)
        self.replay = TensorDictReplayBuffer(storage=LazyTensorStorage(demos.numel()),
                                             batch_size=int(self.cfg.optim.batch_size))
        self.replay.extend(demos.select(*DEMO_KEYS))
        total, every = int(self.cfg.optim.updates), int(self.cfg.optim.updates_per_iteration)
        while self.progress < total:
            yield min(every, total - self.progress)

    def learn(self, updates: int) -> dict[str, float]:
        log = summarise([self.algorithm.update(self.replay.sample()) for _ in range(updates)])
        self.progress += updates
        return {**log, "env_steps": 0, "updates": self.progress, "train/safety_violations_total": 0.0,
                "train/mentor_data_total": self.totals["demo_steps"], "train/mentor_data_share": 1.0}

    def postfix(self, row: dict[str, float]) -> dict:
        return {k.split("/", 1)[1]: round(v, 3) for k, v in row.items() if k.startswith("loss/")}

    def summary(self, out_dir: Path) -> dict:
        training = {"env_steps": 0, "updates": self.progress, "episodes": 0, "safety_violations": 0.0,
                    **self.totals, "mentor_data_total": self.totals["demo_steps"], "mentor_data_share": 1.0}
        return {"method": self.method.name, "algorithm": algorithm_name(str(self.cfg.method)), "training": training}


def train_offline(cfg, out_dir: Path, logger, checkpoint_dir: Path | None = None, resume: bool = False) -> dict:
    """Train ``cfg.method`` (bc or cql) on its demonstrations; returns the final evaluation summary dict."""
    torch.manual_seed(int(cfg.seed))
    run = Run(cfg, OfflineLearner(cfg, Path(out_dir)), logger, checkpoint_dir, total=cfg.optim.updates,
              eval_every=cfg.eval.every_updates, checkpoint_every=cfg.checkpoint.every_updates)
    return run.train(Path(out_dir), resume)


__all__ = ["BCLearner", "BCThenCQL", "CQLLearner", "OfflineLearner", "train_offline"]
