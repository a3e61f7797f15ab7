"""The learner's networks of a recipe config: the actor, and ``PERLHFLoss`` with its critics (their input width:
:func:`pe_rlhf.runtime.world.obs_dim`). A module of its own, so that loading a run folder's actor
(:mod:`pe_rlhf.algorithms.proxy_q.trained_policy`) needs nothing of the env and collector builders
(:mod:`pe_rlhf.algorithms.proxy_q.builders`, which re-exports these).
"""

from __future__ import annotations

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import ForeachSoftUpdate, PERLHFLoss
from pe_rlhf.runtime.world import obs_dim


def build_actor(cfg):
    return make_actor(obs_dim(cfg), hidden=tuple(cfg.loss.hidden))


def build_loss(cfg, actor) -> tuple[PERLHFLoss, ForeachSoftUpdate]:
    """``PERLHFLoss`` of ``cfg.loss``, with HAIM-DRL's disturbance critic when ``disturbance.enabled``."""
    hidden, n = tuple(cfg.loss.hidden), obs_dim(cfg)
    target_entropy = cfg.loss.target_entropy
    disturbance = make_qvalue(n, hidden=hidden) if cfg.disturbance.enabled else None
    loss = PERLHFLoss(
        actor, make_qvalue(n, hidden=hidden), make_qvalue(n, hidden=hidden), disturbance,
        num_qvalue_nets=int(cfg.loss.num_qvalue_nets),
        gamma=float(cfg.loss.gamma), gap_coef=float(cfg.loss.gap_coef),
        gap_margin=None if cfg.loss.gap_margin is None else float(cfg.loss.gap_margin), psi=float(cfg.loss.psi),
        intervention_weight=float(cfg.loss.intervention_weight), cosine_cost=bool(cfg.loss.cosine_cost),
        intervention_critic_action=str(cfg.loss.intervention_critic_action),
        num_intervention_qvalue_nets=int(cfg.loss.num_intervention_qvalue_nets),
        alpha_init=float(cfg.loss.alpha_init),
        target_entropy=target_entropy if target_entropy == "auto" else float(target_entropy), action_dim=2,
        disturbance_weight=float(cfg.loss.disturbance_weight),
        num_disturbance_qvalue_nets=int(cfg.loss.num_disturbance_qvalue_nets),
        failure_target=str(cfg.loss.failure_target), gap_action=str(cfg.loss.gap_action),
        fused_critics=bool(cfg.loss.fused_critics),
    )
    return loss, ForeachSoftUpdate(loss, tau=float(cfg.loss.tau))


__all__ = ["build_actor", "build_loss"]
