"""The online imitation learners: GAIL, and HG-DAgger / IWR with the simulated mentor in the loop.

They plug into :class:`~pe_rlhf.algorithms.baselines.loop.BaselineLearner` like the RL learners (``actor``, ``modules``,
``optimizers``, ``replay_buffers``, ``collector_kwargs``, ``learn``), plus the optional hooks the loop
looks for: ``make_env`` (the collecting env), ``exploration_type``, ``pretrain`` (before the first batch
of a fresh run) and ``training_totals`` (added to ``final_eval.json``'s training section).

- :class:`GAILLearner`: PPO (the PPO baselines' learner) on the reward ``-log(1 - D(s, a))`` in place of
  the env's; before each batch's PPO epochs, ``discriminator.updates_per_batch`` steps of
  :class:`~pe_rlhf.algorithms.baselines.imitation.DiscriminatorLoss` on a demonstration minibatch against a minibatch
  of the batch. The env's reward still makes the logged training returns.
- :class:`InterventionLearner`: the actor drives (deterministically), the mentor takes over when its
  rule says so (:class:`~pe_rlhf.transforms.InterventionTransform`, no physics, no selector). ``pretrain``
  fits BC on the demonstrations (``optim.pretrain_epochs``); after each round of
  ``collector.frames_per_batch`` steps the round's data joins the dataset (HG-DAgger: the takeover steps,
  :func:`~pe_rlhf.algorithms.baselines.imitation.hg_dagger_select`; IWR: every step,
  :func:`~pe_rlhf.algorithms.baselines.imitation.executed_steps`) and BC runs ``optim.epochs`` passes over it
  (IWR: weighted by :func:`~pe_rlhf.algorithms.baselines.imitation.iwr_weights`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType

from pe_rlhf.algorithms.baselines.algorithms import (
    POLICY_KEYS,
    TRANSITION_KEYS,
    PPOLearner,
    _NoTargets,
    _params,
    add_advantages,
    summarise,
)
from pe_rlhf.algorithms.baselines.demos import data_totals, demonstrations
from pe_rlhf.algorithms.baselines.episodes import EpisodeTracker
from pe_rlhf.algorithms.baselines.imitation import (
    DATASET_KEYS,
    DiscriminatorLoss,
    WeightedBCLoss,
    demonstration_rows,
    executed_steps,
    fit_epochs,
    gail_reward,
    hg_dagger_select,
    iwr_weights,
    make_discriminator,
)
from pe_rlhf.modules import make_actor
from pe_rlhf.objectives import make_adam
from pe_rlhf.runtime.update import update
from pe_rlhf.transforms.keys import INTERVENTION, INTERVENTION_START


class GAILLearner(PPOLearner):
    """GAIL: a PPO generator on the discriminator's reward (module docstring)."""

    def __init__(self, cfg, obs_dim: int, run_dir):
        super().__init__(cfg, obs_dim, lagrangian=False)
        d = cfg.discriminator
        demos = demonstrations(cfg, run_dir)
        self.demo_totals = data_totals(demos)
        self.demos = TensorDictReplayBuffer(storage=LazyTensorStorage(demos.numel()), batch_size=int(d.batch_size))
        self.demos.extend(demos.select("observation", "action"))
        self.discriminator = make_discriminator(obs_dim, d.hidden)
        self.discriminator_loss = DiscriminatorLoss(self.discriminator, float(d.grad_penalty))
        self.policy_optimizers = self.optimizers
        self.discriminator_optimizers = {
            "discriminator": make_adam(_params(self.discriminator_loss.discriminator_network_params),
                                              lr=float(d.lr))}
        self.optimizers = {**self.policy_optimizers, **self.discriminator_optimizers}
        self.modules = {**self.modules, "discriminator": self.discriminator_loss}
        self.env_steps = 0

    def discriminator_step(self, policy_steps: TensorDictBase) -> dict[str, float]:
        expert = self.demos.sample()
        idx = torch.randint(0, policy_steps.numel(), (expert.numel(),))
        td = TensorDict({"observation": expert.get("observation"), "action": expert.get("action"),
                         "collector_observation": policy_steps.get("observation")[idx],
                         "collector_action": policy_steps.get("action")[idx]}, batch_size=expert.batch_size)
        return update(self.discriminator_loss, self.discriminator_optimizers, _NoTargets(), td,
                      self.cfg.optim.max_grad_norm)

    def learn(self, batch: TensorDictBase, frames: int, tracker: EpisodeTracker) -> dict[str, float]:
        data = batch.select(*TRANSITION_KEYS, *POLICY_KEYS).reshape(-1)
        self.env_steps += data.numel()
        disc = [self.discriminator_step(data) for _ in range(int(self.cfg.discriminator.updates_per_batch))]
        with torch.no_grad():
            d_policy = self.discriminator(data.select("observation", "action")).get("d_prob")
            d_expert = self.discriminator(self.demos.sample().select("observation", "action")).get("d_prob")
        reward = gail_reward(self.discriminator, data)
        data.set(("next", "reward"), reward)  # the generator's reward; the tracker logged the env's
        log = summarise(disc)
        log.update(summarise(self.fit(add_advantages(self.loss, data), self.objective, self.policy_optimizers)))
        self.objective.adapt(log["train/kl"])
        log.update({"train/kl_coef": float(self.objective.kl_coef), "train/gail_reward": float(reward.mean()),
                    "train/d_policy": float(d_policy.mean()), "train/d_expert": float(d_expert.mean()),
                    **self._data_columns()})
        return log

    def _data_columns(self) -> dict[str, float]:
        demo = self.demo_totals["demo_steps"]
        return {"train/mentor_data_total": demo, "train/mentor_data_share": demo / (demo + self.env_steps)}

    def training_totals(self) -> dict[str, float]:
        return {**self.demo_totals, **{k.split("/", 1)[1]: v for k, v in self._data_columns().items()}}


class TakeoverCounts(nn.Module):
    """The human-in-the-loop run's cumulative counts, as buffers (checkpointed with the modules)."""

    def __init__(self):
        super().__init__()
        for name in ("env_steps", "takeover_steps", "takeover_starts", "demo_steps", "demo_safety_violations"):
            self.register_buffer(name, torch.zeros((), dtype=torch.float64))

    def add(self, batch: TensorDictBase) -> dict[str, float]:
        nxt = batch.get("next")
        steps, takeovers = float(batch.numel()), float(nxt.get(INTERVENTION).sum())
        self.env_steps += steps
        self.takeover_steps += takeovers
        self.takeover_starts += float(nxt.get(INTERVENTION_START).sum())
        return {"train/takeover_rate": takeovers / max(steps, 1.0)}

    def columns(self, dataset_size: int) -> dict[str, float]:
        mentor = float(self.demo_steps + self.takeover_steps)
        return {"train/takeover_count": float(self.takeover_starts),
                "train/takeover_steps_total": float(self.takeover_steps),
                "train/takeover_data_usage": float(self.takeover_steps / self.env_steps.clamp_min(1.0)),
                "train/mentor_data_total": mentor, "train/mentor_data_share": mentor / max(dataset_size, 1),
                "train/dataset_size": float(dataset_size)}


class InterventionLearner:
    """HG-DAgger (``weighted=False``: takeover steps only) or IWR (``weighted=True``: every step, re-weighted)."""

    exploration_type = ExplorationType.DETERMINISTIC  # the novice drives its best guess; the mentor corrects it

    def __init__(self, cfg, obs_dim: int, run_dir, weighted: bool):
        self.cfg, self.run_dir, self.weighted = cfg, run_dir, weighted
        self.actor = make_actor(obs_dim, hidden=tuple(cfg.loss.hidden))
        self.loss = WeightedBCLoss(self.actor, str(cfg.loss.function))
        self.optimizers = {"actor": make_adam(_params(self.loss.actor_network_params), lr=float(cfg.optim.lr))}
        self.counts = TakeoverCounts()
        self.modules = {"loss": self.loss, "counts": self.counts}
        size = int(cfg.data.steps) + int(cfg.collector.total_frames)
        self.dataset = TensorDictReplayBuffer(storage=LazyTensorStorage(size))
        self.replay_buffers = {"dataset": self.dataset}

    def make_env(self, env_config):
        """The driving env with the mentor's takeovers (``InterventionTransform`` without physics/selector)."""
        from pe_rlhf.envs.torchrl_env import make_env
        from pe_rlhf.runtime.world import build_mentor
        from pe_rlhf.transforms import InterventionTransform

        env = make_env(env_config)
        env.append_transform(InterventionTransform(build_mentor(self.cfg)))
        return env

    def collector_kwargs(self, frames_done: int) -> dict:
        return {}

    def fit(self, epochs: int) -> dict[str, float]:
        data = self.dataset.storage[:len(self.dataset)]
        o = self.cfg.optim
        weights = iwr_weights(data) if self.weighted else None
        return summarise(fit_epochs(self.loss, self.optimizers, data.select(*DATASET_KEYS), epochs,
                                    int(o.batch_size), o.max_grad_norm, weights))

    def pretrain(self) -> dict[str, float]:
        """BC on the demonstrations, before the first round."""
        demos = demonstrations(self.cfg, self.run_dir)
        totals = data_totals(demos)
        self.counts.demo_steps.fill_(totals["demo_steps"])
        self.counts.demo_safety_violations.fill_(totals["demo_safety_violations"])
        self.dataset.extend(demonstration_rows(demos))
        log = self.fit(int(self.cfg.optim.pretrain_epochs))
        log.update(self.counts.columns(len(self.dataset)))
        return log

    def learn(self, batch: TensorDictBase, frames: int, tracker: EpisodeTracker) -> dict[str, float]:
        flat = batch.reshape(-1)
        log = self.counts.add(flat)
        new = executed_steps(flat) if self.weighted else hg_dagger_select(flat)
        if len(new):  # (TensorDict.numel() of an empty batch is 1)
            self.dataset.extend(new)
        log.update(self.fit(int(self.cfg.optim.epochs)))
        log.update(self.counts.columns(len(self.dataset)))
        return log

    def training_totals(self) -> dict[str, float]:
        columns = self.counts.columns(len(self.dataset))
        return {"demo_steps": float(self.counts.demo_steps),
                "demo_safety_violations": float(self.counts.demo_safety_violations),
                **{k.split("/", 1)[1]: v for k, v in columns.items()}}
