"""The learner's networks of a recipe config: the actor, and ``PERLHFLoss`` with its critics (their input width:
:func:`pe_rlhf.runtime.world.obs_dim`). A module of its own, so that loading a run folder's actor
(:mod:`pe_rlhf.algorithms.proxy_q.trained_policy`) needs nothing of the env and collector builders
(:mod:`pe_rlhf.algorithms.proxy_q.builders`, which re-exports these).
"""

from __future__ import annotations

from pe_rlhf.modules import make_actor, make_deterministic_actor, make_qvalue
from pe_rlhf.objectives import ForeachSoftUpdate, PERLHFLoss, ProxyValueLoss
from pe_rlhf.runtime.world import obs_dim


def uses_proxy_values(cfg) -> bool:
    """Whether the run learns with :class:`~pe_rlhf.objectives.ProxyValueLoss` (``loss.objective=proxy_value``)."""
    return str(cfg.loss.get("objective", "paper")) == "proxy_value"


def build_actor(cfg):
    """The deterministic TD3 actor for ``loss.objective=proxy_value``, else the TanhNormal SAC actor."""
    make = make_deterministic_actor if uses_proxy_values(cfg) else make_actor
    return make(obs_dim(cfg), hidden=tuple(cfg.loss.hidden))


def build_loss(cfg, actor) -> tuple[PERLHFLoss | ProxyValueLoss, ForeachSoftUpdate]:
    """The loss of ``cfg.loss``: ``ProxyValueLoss`` (``objective=proxy_value``) or ``PERLHFLoss``, the latter with
    HAIM-DRL's disturbance critic when ``disturbance.enabled``."""
    hidden, n = tuple(cfg.loss.hidden), obs_dim(cfg)
    layer_norm = bool(cfg.loss.layer_norm)
    if uses_proxy_values(cfg):
        c = cfg.loss
        loss = ProxyValueLoss(actor, make_qvalue(n, hidden=hidden, layer_norm=layer_norm),
                              q_value_bound=float(c.q_value_bound), gamma=float(c.gamma),
                              target_noise=float(c.target_noise), policy_delay=int(c.policy_delay), bc_weight=float(c.bc_weight),
                              mask_td_at_takeover_start=bool(c.mask_td_at_takeover_start),
                              proxy_reduction=str(c.proxy_reduction))
        return loss, ForeachSoftUpdate(loss, tau=float(c.tau))
    target_entropy = cfg.loss.target_entropy
    d = cfg.disturbance  # HAIM-DRL's group: its weight and critics only with enabled
    disturbance = make_qvalue(n, hidden=hidden) if d.enabled else None
    loss = PERLHFLoss(
        actor, make_qvalue(n, hidden=hidden, layer_norm=layer_norm), make_qvalue(n, hidden=hidden), disturbance,
        num_qvalue_nets=int(cfg.loss.num_qvalue_nets),
        gamma=float(cfg.loss.gamma), gap_coef=float(cfg.loss.gap_coef),
        psi=float(cfg.loss.psi),
        intervention_weight=float(cfg.loss.intervention_weight), cosine_cost=bool(cfg.loss.cosine_cost),
        num_intervention_qvalue_nets=int(cfg.loss.num_intervention_qvalue_nets),
        alpha_init=float(cfg.loss.alpha_init),
        target_entropy=target_entropy if target_entropy == "auto" else float(target_entropy), action_dim=2,
        **({"disturbance_weight": float(d.weight), "num_disturbance_qvalue_nets": int(d.num_qvalue_nets)}
           if d.enabled else {}),
        failure_target=str(cfg.loss.failure_target),
    )
    return loss, ForeachSoftUpdate(loss, tau=float(cfg.loss.tau))


__all__ = ["build_actor", "build_loss", "uses_proxy_values"]
