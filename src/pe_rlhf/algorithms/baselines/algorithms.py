"""The baselines' learners: what each does with one collected batch.

- :class:`SACLearner` (SAC-RS, SAC-Lag): TorchRL's ``SACLoss`` / :class:`~pe_rlhf.objectives.SACLagLoss`,
  a replay buffer, ``optim.updates_per_batch`` updates per batch (one per env step by default) once
  ``collector.learning_starts`` frames are in; SAC-Lag's ``lambda`` takes one projected dual step per
  batch from the mean cost of the last ``constraint.window`` finished episodes.
- :class:`PPOLearner` (PPO-RS, PPO-Lag): GAE on the whole batch (reward, and cost for PPO-Lag), then
  ``optim.epochs`` passes over it in minibatches of TorchRL's ``ClipPPOLoss`` /
  :class:`~pe_rlhf.objectives.PPOLagLoss` plus RLlib's adaptive KL penalty (:class:`KLPenalty`, the
  paper's "KL coefficient"); PPO-Lag's ``lambda`` steps once per batch, before the epochs.
- :class:`CPOLearner`: GAE, one :meth:`~pe_rlhf.objectives.CPOLoss.policy_step` per batch with the
  window's mean episode cost, then the two value nets fitted as PPO's critic is.

Each learner has ``actor`` (the collecting policy), ``modules`` / ``optimizers`` / ``replay_buffers`` (what
a checkpoint saves: every learned number, ``lambda`` and the KL coefficient included), ``collector_kwargs``
and ``learn(batch, frames, tracker) -> {column: number}``.
Gradient steps go through :func:`pe_rlhf.runtime.update.update` (per-optimizer clipping, non-finite
checks naming the culprit).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torch.distributions import Normal, kl_divergence
from torchrl.data import Bounded, LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer
from torchrl.modules import MLP, ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, SACLoss, ValueEstimators

from pe_rlhf.algorithms.baselines.episodes import EpisodeTracker
from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import CPOLoss, ForeachSoftUpdate, LagrangeMultiplier, PPOLagLoss, SACLagLoss, make_adam
from pe_rlhf.objectives.cpo import base_normal
from pe_rlhf.runtime.update import update

# What a learner keeps of a collected step (the env's info keys are for the tracker only).
TRANSITION_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "cost"),
                   ("next", "done"), ("next", "terminated"))
POLICY_KEYS = ("action_log_prob", "loc", "scale")  # on-policy: the behaviour policy's log-prob and Gaussian


# --------------------------------------------------------------------------- networks


def make_stochastic_actor(obs_dim: int, hidden) -> ProbabilisticActor:
    """:func:`~pe_rlhf.modules.make_actor`'s network (same ``state_dict``, so ``actor.safetensors`` loads into it)
    writing ``action_log_prob`` as well, which the on-policy losses read as the behaviour's log-prob."""
    base = make_actor(obs_dim, hidden=tuple(hidden))
    net, sampler = base.module[0], base.module[-1]
    return ProbabilisticActor(net, in_keys=["loc", "scale"], spec=base.spec["action"],
                              distribution_class=sampler.distribution_class,
                              distribution_kwargs=dict(sampler.distribution_kwargs), return_log_prob=True)


def make_value(obs_dim: int, hidden, out_key: str) -> TensorDictModule:
    """``V(s)``: reads ``observation``, writes ``out_key`` ``(..., 1)``."""
    return TensorDictModule(MLP(in_features=obs_dim, out_features=1, num_cells=list(hidden), activation_class=nn.ReLU),
                            in_keys=["observation"], out_keys=[out_key])


def _params(*groups) -> list[torch.Tensor]:
    return [p for group in groups for p in group.flatten_keys().values()]


def summarise(outputs: list[dict[str, float]]) -> dict[str, float]:
    """Mean of each returned scalar over a batch's updates: ``loss_x`` -> ``loss/x``, others -> ``train/x``."""
    values: dict[str, list[float]] = defaultdict(list)
    for out in outputs:
        for key, value in out.items():
            values[key].append(value)
    return {(f"loss/{k[5:]}" if k.startswith("loss_") else f"train/{k}"): float(np.mean(v)) for k, v in values.items()}


def lagrange_multiplier(cfg) -> LagrangeMultiplier:
    c = cfg.constraint
    return LagrangeMultiplier(float(c.cost_limit), init=float(c.lambda_init), lr=float(c.lambda_lr))


class _NoTargets:
    """``update()``'s target-network step for losses without target networks (PPO, CPO)."""

    def step(self) -> None:
        pass


# --------------------------------------------------------------------------- SAC-RS / SAC-Lag


class SACLearner:
    """SAC on the env reward (SAC-RS), or SAC-Lag with a cost critic and ``lambda`` (``lagrangian``)."""

    def __init__(self, cfg, obs_dim: int, lagrangian: bool):
        o, lc = cfg.optim, cfg.loss
        self.cfg, self.lagrangian = cfg, lagrangian
        self.actor = make_actor(obs_dim, hidden=tuple(lc.hidden))
        kwargs = {"num_qvalue_nets": int(lc.num_qvalue_nets), "loss_function": "l2", "alpha_init": float(lc.alpha_init),
                  "deactivate_vmap": bool(lc.deactivate_vmap),
                  "action_spec": Bounded(-1.0, 1.0, (2,)),
                  "target_entropy": lc.target_entropy if lc.target_entropy == "auto" else float(lc.target_entropy)}
        qvalue = make_qvalue(obs_dim, hidden=tuple(lc.hidden))
        if lagrangian:
            self.loss = SACLagLoss(self.actor, qvalue, make_qvalue(obs_dim, hidden=tuple(lc.hidden)),
                                   lagrange_multiplier=lagrange_multiplier(cfg),
                                   num_cost_qvalue_nets=int(lc.num_cost_qvalue_nets),
                                   cost_aggregate=str(lc.cost_aggregate), **kwargs)
        else:
            self.loss = SACLoss(self.actor, qvalue, **kwargs)
        self.loss.make_value_estimator(gamma=float(lc.gamma))
        self.soft_update = ForeachSoftUpdate(self.loss, tau=float(lc.tau))
        lr = float(o.lr)
        self.optimizers = {"actor": make_adam(_params(self.loss.actor_network_params), lr=lr),
                           "qvalue": make_adam(_params(self.loss.qvalue_network_params), lr=lr),
                           "alpha": make_adam([self.loss.log_alpha], lr=lr)}
        if lagrangian:
            self.optimizers["cost_qvalue"] = make_adam(_params(self.loss.cost_qvalue_network_params), lr=lr)
        # LazyTensorStorage allocates all its slots at the first write: no more than the run can fill.
        size = min(int(cfg.replay_buffer.size), int(cfg.collector.total_frames))
        self.replay = TensorDictReplayBuffer(storage=LazyTensorStorage(size),
                                             batch_size=int(cfg.replay_buffer.batch_size))
        self.replay_buffers = {"replay": self.replay}
        self.modules = {"loss": self.loss}

    def collector_kwargs(self, frames_done: int) -> dict:
        """Uniform random actions for the first ``collector.init_random_frames`` frames of the run."""
        return {"init_random_frames": max(int(self.cfg.collector.init_random_frames) - frames_done, 0)}

    def learn(self, batch: TensorDictBase, frames: int, tracker: EpisodeTracker) -> dict[str, float]:
        self.replay.extend(batch.select(*TRANSITION_KEYS).reshape(-1))
        log = {}
        if frames >= int(self.cfg.collector.learning_starts):
            window = tracker.window_cost()
            if self.lagrangian and window is not None:
                self.loss.lagrange_multiplier.update(window)  # once per batch, before its updates
            max_norm, precision = self.cfg.optim.max_grad_norm, str(self.cfg.optim.precision)
            log.update(summarise([update(self.loss, self.optimizers, self.soft_update, self.replay.sample(), max_norm,
                                         precision) for _ in range(int(self.cfg.optim.updates_per_batch))]))
        if self.lagrangian:
            log["train/lambda"] = float(self.loss.lagrange_multiplier.value.detach())
            log.pop("train/lagrange_multiplier", None)  # the value the updates saw: train/lambda says it
        return log


# --------------------------------------------------------------------------- PPO-RS / PPO-Lag


class KLPenalty(nn.Module):
    """A PPO loss plus RLlib's KL penalty ``loss_kl = kl_coef * mean_s KL(pi_old(.|s) || pi(.|s))``.

    RLlib's PPO (whose table the paper's appendix reproduces) adds it to the clipped surrogate and adapts
    ``kl_coef`` after each batch (:meth:`adapt`): x1.5 when the batch's mean KL exceeded ``2 * kl_target``,
    x0.5 below ``kl_target / 2``. The KL is between the base Gaussians (the tanh is a bijection), the old one
    from the batch's ``loc``/``scale``. Writes ``loss_kl`` and ``kl`` besides the wrapped loss's outputs;
    ``kl_coef`` is a buffer (checkpointed).
    """

    def __init__(self, loss: ClipPPOLoss, kl_coef: float, kl_target: float | None):
        super().__init__()
        self.loss, self.kl_target = loss, kl_target
        self.register_buffer("kl_coef", torch.tensor(float(kl_coef)))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.loss(tensordict)
        actor = self.loss.actor_network
        with self.loss.actor_network_params.to_module(actor, preserve_module_state=False):
            dist = actor.get_dist(tensordict.select(*actor.in_keys, strict=False))
        old = Normal(tensordict.get("loc"), tensordict.get("scale"))
        kl = kl_divergence(old, base_normal(dist)).sum(-1).mean()
        out.set("loss_kl", self.kl_coef * kl)
        out.set("kl", kl.detach())
        return out

    @torch.no_grad()
    def adapt(self, mean_kl: float) -> None:
        if self.kl_target is None:
            return
        if mean_kl > 2.0 * self.kl_target:
            self.kl_coef.mul_(1.5)
        elif mean_kl < 0.5 * self.kl_target:
            self.kl_coef.mul_(0.5)


def minibatch_epochs(buffer: TensorDictReplayBuffer, data: TensorDictBase, epochs: int, step) -> list[dict[str, float]]:
    """``epochs`` passes over ``data`` (flat) in shuffled minibatches of ``buffer``'s batch size (a buffer
    with TorchRL's sampler without replacement, emptied first; a remainder smaller than a minibatch sits
    out that epoch); ``step(minibatch)`` returns scalars."""
    buffer.empty()
    buffer.extend(data.reshape(-1))
    return [step(buffer.sample()) for _ in range(epochs) for _ in range(data.numel() // buffer.batch_size)]


@torch.no_grad()
def add_advantages(loss, data: TensorDictBase) -> TensorDictBase:
    """GAE on a whole batch with the critics as they are: ``advantage``, ``value_target`` and, for losses
    with a cost critic, ``cost_advantage``, ``cost_value_target`` (written into ``data``)."""
    loss.value_estimator(data)
    if hasattr(loss, "cost_value_estimator"):
        loss.cost_value_estimator(data)
    return data


class _OnPolicyLearner:
    """What PPO and CPO share: the actor with log-probs, critics, GAE, minibatch epochs."""

    def __init__(self, cfg, obs_dim: int):
        self.cfg = cfg
        self.actor = make_stochastic_actor(obs_dim, cfg.loss.hidden)
        self.batch_buffer = TensorDictReplayBuffer(  # one collected batch, for the minibatch epochs
            storage=LazyTensorStorage(int(cfg.collector.frames_per_batch)),
            sampler=SamplerWithoutReplacement(drop_last=True), batch_size=int(cfg.optim.minibatch_size))
        self.replay_buffers: dict = {}  # on-policy: nothing outlives its batch

    def value_net(self, obs_dim: int, out_key: str) -> TensorDictModule:
        return make_value(obs_dim, self.cfg.loss.hidden, out_key)

    def _use_gae(self, loss) -> None:
        loss.make_value_estimator(ValueEstimators.GAE, gamma=float(self.cfg.loss.gamma),
                                  lmbda=float(self.cfg.loss.gae_lambda))

    def collector_kwargs(self, frames_done: int) -> dict:
        return {}

    def batch_data(self, batch: TensorDictBase) -> TensorDictBase:
        return add_advantages(self.loss, batch.select(*TRANSITION_KEYS, *POLICY_KEYS).reshape(-1))

    def fit(self, data: TensorDictBase, objective, optimizers: dict) -> list[dict[str, float]]:
        o = self.cfg.optim
        return minibatch_epochs(self.batch_buffer, data, int(o.epochs),
                                lambda mb: update(objective, optimizers, _NoTargets(), mb, o.max_grad_norm))


class PPOLearner(_OnPolicyLearner):
    """PPO (clipped surrogate + adaptive KL penalty) on the env reward; PPO-Lag with ``lagrangian``."""

    def __init__(self, cfg, obs_dim: int, lagrangian: bool):
        super().__init__(cfg, obs_dim)
        lc, self.lagrangian = cfg.loss, lagrangian
        kwargs = {"clip_epsilon": float(lc.clip_epsilon), "entropy_bonus": float(lc.entropy_coef) > 0,
                  "entropy_coeff": float(lc.entropy_coef), "critic_coeff": float(lc.critic_coef),
                  "normalize_advantage": bool(lc.normalize_advantage)}
        critic = self.value_net(obs_dim, "state_value")
        if lagrangian:
            self.loss = PPOLagLoss(self.actor, critic, self.value_net(obs_dim, "state_cost_value"),
                                   lagrange_multiplier=lagrange_multiplier(cfg), **kwargs)
        else:
            self.loss = ClipPPOLoss(self.actor, critic, **kwargs)
        self._use_gae(self.loss)
        self.objective = KLPenalty(self.loss, float(lc.kl_coef), None if lc.kl_target is None else float(lc.kl_target))
        critics = [self.loss.critic_network_params] + ([self.loss.cost_critic_network_params] if lagrangian else [])
        lr = float(cfg.optim.lr)
        self.optimizers = {"actor": make_adam(_params(self.loss.actor_network_params), lr=lr),
                           "critic": make_adam(_params(*critics), lr=lr)}
        self.modules = {"loss": self.objective}  # kl_coef included

    def learn(self, batch: TensorDictBase, frames: int, tracker: EpisodeTracker) -> dict[str, float]:
        data = self.batch_data(batch)
        window = tracker.window_cost()
        if self.lagrangian and window is not None:
            self.loss.lagrange_multiplier.update(window)  # once per batch, before the epochs use it
        log = summarise(self.fit(data, self.objective, self.optimizers))
        self.objective.adapt(log["train/kl"])
        log["train/kl_coef"] = float(self.objective.kl_coef)
        if self.lagrangian:
            log["train/lambda"] = float(self.loss.lagrange_multiplier.value.detach())
            log.pop("train/lagrange_multiplier", None)
        return log


# --------------------------------------------------------------------------- CPO


class CPOLearner(_OnPolicyLearner):
    """CPO: one constrained trust-region policy step per batch, then the reward and cost value nets."""

    def __init__(self, cfg, obs_dim: int):
        super().__init__(cfg, obs_dim)
        lc = cfg.loss
        self.loss = CPOLoss(self.actor, self.value_net(obs_dim, "state_value"),
                            self.value_net(obs_dim, "state_cost_value"), cost_limit=float(cfg.constraint.cost_limit),
                            target_kl=float(lc.target_kl), cg_iterations=int(lc.cg_iterations),
                            cg_damping=float(lc.cg_damping), backtrack_ratio=float(lc.backtrack_ratio),
                            max_backtracks=int(lc.max_backtracks))
        self._use_gae(self.loss)
        critics = _params(self.loss.critic_network_params, self.loss.cost_critic_network_params)
        self.optimizers = {"critics": make_adam(critics, lr=float(cfg.optim.lr))}
        self.modules = {"loss": self.loss}

    def learn(self, batch: TensorDictBase, frames: int, tracker: EpisodeTracker) -> dict[str, float]:
        data = self.batch_data(batch)
        window = tracker.window_cost()
        # Before the first episode ends, the cost so far of the one in progress (a lower bound on J_c).
        episode_cost = window if window is not None else tracker.running_cost
        step = self.loss.policy_step(data, episode_cost)
        log = {f"train/cpo_{k}": float(v) for k, v in step.items()}
        log.update(summarise(self.fit(data, self.loss, self.optimizers)))
        return log

