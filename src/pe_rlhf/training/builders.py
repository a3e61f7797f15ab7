"""Builders shared by the recipes: env with interventions, collector, replay buffer, loss, optimisers.

Each takes the recipe config (an OmegaConf ``DictConfig`` validated by
:func:`pe_rlhf.training.config.validate_config`) and returns a ready TorchRL object,
as TorchRL's ``sota-implementations/*/utils.py`` do.
"""

from __future__ import annotations

import importlib

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import SoftUpdate

from pe_rlhf.envs.torchrl_env import make_env
from pe_rlhf.mentors import Mentor, make_mentor
from pe_rlhf.modules import QEnsemble, make_actor, make_qvalue
from pe_rlhf.objectives import PERLHFLoss
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.transforms import HybridActionSelector, InterventionTransform

OBS_DIM = 250


def build_mentor(cfg) -> Mentor:
    """A mentor by preset name, or a user's class given as ``package.module:Name``."""
    name = str(cfg.mentor.name)
    if ":" in name:
        module_name, _, attr = name.partition(":")
        mentor = getattr(importlib.import_module(module_name), attr)()
        if not isinstance(mentor, Mentor):
            raise TypeError(f"mentor.name={name!r} built a {type(mentor).__name__}, not a pe_rlhf Mentor")
        return mentor
    kwargs = dict(cfg.mentor.get("kwargs") or {})
    return make_mentor(name, int(cfg.mentor.seed), **kwargs)


def build_physics(cfg) -> IDMMobilPolicy | None:
    from pe_rlhf.training.config import physics_config

    return IDMMobilPolicy(physics_config(cfg)) if cfg.physics.enabled else None


def build_q_ensemble(cfg) -> QEnsemble | None:
    if not cfg.selector.enabled:
        return None
    return QEnsemble(OBS_DIM, num_members=int(cfg.selector.num_members), hidden=tuple(cfg.selector.hidden))


def build_train_env(cfg, env_config, mentor: Mentor, ensemble: QEnsemble | None, physics):
    """The TorchRL driving env with ``InterventionTransform`` (PE-RLHF with a selector, HACO without)."""
    env = make_env(env_config)
    selector = None
    if ensemble is not None:
        selector = HybridActionSelector(ensemble, float(cfg.selector.epsilon_select),
                                        cfg.selector.variance_threshold)
    env.append_transform(InterventionTransform(mentor, selector, physics if selector else None,
                                               warmup_steps=int(cfg.collector.warmup_steps)))
    env.set_seed(int(cfg.seed))
    return env


def build_actor(cfg):
    return make_actor(OBS_DIM, hidden=tuple(cfg.loss.hidden))


def build_collector(cfg, env, actor, total_frames: int | None = None) -> Collector:
    """A single-process collector over the env (the transform drives this process's simulator)."""
    frames = int(cfg.collector.total_frames) if total_frames is None else int(total_frames)
    return Collector(env, actor, frames_per_batch=int(cfg.collector.frames_per_batch), total_frames=frames)


def build_replay_buffer(cfg) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=LazyTensorStorage(int(cfg.replay_buffer.size)),
                                  batch_size=int(cfg.replay_buffer.batch_size))


def build_loss(cfg, actor) -> tuple[PERLHFLoss, SoftUpdate]:
    hidden = tuple(cfg.loss.hidden)
    target_entropy = cfg.loss.target_entropy
    loss = PERLHFLoss(
        actor, make_qvalue(OBS_DIM, hidden=hidden), make_qvalue(OBS_DIM, hidden=hidden),
        num_qvalue_nets=int(cfg.loss.num_qvalue_nets),
        gamma=float(cfg.loss.gamma), gap_coef=float(cfg.loss.gap_coef), psi=float(cfg.loss.psi),
        intervention_weight=float(cfg.loss.intervention_weight), cosine_cost=bool(cfg.loss.cosine_cost),
        intervention_critic_action=str(cfg.loss.intervention_critic_action),
        num_intervention_qvalue_nets=int(cfg.loss.num_intervention_qvalue_nets),
        alpha_init=float(cfg.loss.alpha_init),
        target_entropy=target_entropy if target_entropy == "auto" else float(target_entropy), action_dim=2,
    )
    return loss, SoftUpdate(loss, tau=float(cfg.loss.tau))


def build_optimizers(cfg, loss: PERLHFLoss) -> dict[str, torch.optim.Optimizer]:
    """One Adam per loss term, each over the parameters that term trains."""
    lr = float(cfg.optim.lr)
    return {
        "actor": torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=lr),
        "qvalue": torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=lr),
        "intervention_qvalue": torch.optim.Adam(
            loss.intervention_qvalue_network_params.flatten_keys().values(), lr=lr),
        "alpha": torch.optim.Adam([loss.log_alpha], lr=lr),
    }
