"""The RL and safe-RL baselines' structured configs (SAC-RS, SAC-Lag, PPO-RS, PPO-Lag, CPO), the groups every
baseline shares and :data:`METHODS`: the one place for every field's default, type and rule.

One dataclass per method (``SacLagConfig``, ...; the imitation methods' in
:mod:`pe_rlhf.algorithms.baselines.imitation_schema`, all of them in
:data:`pe_rlhf.algorithms.baselines.config.SCHEMAS`) built from one dataclass per group; each field is a
:func:`~pe_rlhf.runtime.config_schema.knob` with its default, its declared type and its rule
(:mod:`pe_rlhf.runtime.config_rules`: what is allowed, in the words of the error). Values are the paper's appendix
tables (SAC/SAC-Lag, PPO/PPO-Lag, CPO) where they give one ("paper" beside a field); every other value says where it
comes from. Hydra composes a recipe's ``config.yaml`` over its method's schema
(:mod:`pe_rlhf.algorithms.baselines.config`).

Families (:data:`METHODS`): ``sac`` (SAC-RS, SAC-Lag: off-policy), ``ppo`` (PPO-RS, PPO-Lag), ``cpo``, and the
imitation families ``offline`` (BC, CQL), ``gail`` and ``hil`` (HG-DAgger, IWR). "RS" is the env's shaped reward
(spec §4) as it is; ``*_lag`` and ``cpo`` add the constraint ``mean episode cost <= constraint.cost_limit`` on the
env's ``("next", "cost")``.

The paper's cost limit is 1 per episode, for MetaDrive's safe env, where an episode goes on after a collision and
costs pile up. Here an episode ends at its first collision (:mod:`pe_rlhf.envs.driving_env`), so an episode costs
0 or 1 and ``J_c <= 1`` always: with the limit 1, ``lambda`` never rises and CPO's constraint is never violated
(at best ``c = 0``). ``constraint.cost_limit`` below 1 is then the crash rate allowed per episode (e.g. 0.2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from pe_rlhf.algorithms.baselines.config_profiles import PROFILE_NAMES
from pe_rlhf.modules.precision import PRECISIONS
from pe_rlhf.runtime.config_rules import (
    SPLITS,
    rule_bool,
    rule_choice,
    rule_hidden,
    rule_int,
    rule_number,
    rule_optional,
    rule_target_entropy,
)
from pe_rlhf.runtime.config_schema import LoggerConfig, knob, open_group


@dataclass(frozen=True)
class Method:
    """A baseline: its display name, its family (``sac``: off-policy, ``ppo``/``cpo``: on-policy; ``offline``,
    ``gail``, ``hil``: imitation) and whether it has a Lagrange multiplier."""

    name: str
    family: str
    lagrangian: bool


METHODS: dict[str, Method] = {
    "sac_rs": Method("SAC-RS", "sac", False),
    "sac_lag": Method("SAC-Lag", "sac", True),
    "ppo_rs": Method("PPO-RS", "ppo", False),
    "ppo_lag": Method("PPO-Lag", "ppo", True),
    "cpo": Method("CPO", "cpo", False),
    # imitation, offline and human-in-the-loop
    "bc": Method("BC", "offline", False),
    "cql": Method("CQL", "offline", False),
    "gail": Method("GAIL", "gail", False),
    "hg_dagger": Method("HG-DAgger", "hil", False),
    "iwr": Method("IWR", "hil", False),
}
IMITATION_FAMILIES = ("offline", "gail", "hil")

POSITIVE = rule_number(0, lo_open=True)
GRAD_NORM = rule_optional(POSITIVE)  # null: no clipping (RLlib's default)
# Any pe_rlhf.envs.config.DrivingConfig field; unset fields keep its defaults (horizon 1000, the train split).
# The paper's SAC table gives an env horizon of 1500; the env's 1000 is kept so that every method is trained and
# tested on the same episodes. lane_features: the lane summary beside the lidar (pe_rlhf.envs.observation): every
# Table-1 row uses it.
ENV_DEFAULTS = {"lane_features": True}


# --------------------------------------------------------------------------- groups shared by every method


@dataclass
class EvalConfig:
    """Deterministic actions, no mentor; the final evaluation uses the same settings."""

    every_frames: int = knob(100_000, rule_int(0))  # 0: only the final evaluation
    episodes: int = knob(50, rule_int(1))  # the first N scenes of the split (the test split has 50)
    split: str = knob("test", rule_choice(*SPLITS))  # train | validation | test


@dataclass
class CheckpointConfig:
    """Networks, optimisers, lambda, replay buffer or dataset, RNG, counters; ``--resume DIR`` continues."""

    every_frames: int = knob(50_000, rule_int(0))  # 0: only at the end
    keep: int = knob(2, rule_int(1))


# --------------------------------------------------------------------------- SAC-RS, SAC-Lag


@dataclass
class SacCollectorConfig:
    total_frames: int = knob(1_000_000, rule_int(1))  # the paper's budget for the RL baselines (Table 1: 1M env steps)
    frames_per_batch: int = knob(100, rule_int(1))  # env steps per iteration (not in the SAC table; PE-RLHF's 100)
    learning_starts: int = knob(10_000, rule_int(0))  # paper: "steps before learning start"
    # uniform random actions first (TorchRL's SAC habit); 0: the initial policy samples, as RLlib
    init_random_frames: int = knob(0, rule_int(0))


@dataclass
class ReplayBufferConfig:
    size: int = knob(1_000_000, rule_int(1))  # not in the paper: every transition of the 1M budget (RLlib's SAC)
    batch_size: int = knob(256, rule_int(1))  # not in the paper: RLlib's SAC train batch


@dataclass
class SacOptimConfig:
    lr: float = knob(1.0e-4, POSITIVE)  # paper (actor, critics and alpha)
    updates_per_batch: int = knob(100, rule_int(1))  # one gradient step per env step
    max_grad_norm: Optional[float] = knob(None, GRAD_NORM)  # null: no clipping (RLlib's default)
    # fp32 | bf16: bf16 autocast in the updates, fp32 weights and outputs (pe_rlhf.modules.precision)
    precision: str = knob("fp32", rule_choice(*PRECISIONS))


@dataclass
class SacLossConfig:
    """TorchRL SACLoss (twin Q, target networks by SoftUpdate)."""

    gamma: float = knob(0.99, rule_number(0, 1))  # paper
    tau: float = knob(0.005, rule_number(0, 1, lo_open=True))  # paper
    num_qvalue_nets: int = knob(2, rule_int(1))
    target_entropy: Any = knob("auto", rule_target_entropy)  # auto = -dim(A) = -2
    alpha_init: float = knob(1.0, POSITIVE)
    hidden: list[int] = knob([256, 256], rule_hidden)  # actor and critics (not in the paper; PE-RLHF's)
    # TorchRL's option: the critics in a loop, not vmap's batched matmul (~10% faster on CPU)
    deactivate_vmap: bool = knob(True, rule_bool)


@dataclass
class SacLagLossConfig(SacLossConfig):
    """SACLagLoss: SACLoss plus a twin cost critic on the env's cost."""

    num_cost_qvalue_nets: int = knob(2, rule_int(1))
    # max | mean | min over the cost critics (max: pessimistic about cost)
    cost_aggregate: str = knob("max", rule_choice("max", "mean", "min"))


@dataclass
class SacLagConstraintConfig:
    """lambda: one projected dual step per batch once learning has started."""

    # paper: mean cost per episode. Here an episode ends at its first collision, so it costs 0 or 1 and a limit
    # of 1 never binds; below 1 it is the crash rate allowed (e.g. 0.2)
    cost_limit: float = knob(1.0, rule_number(0))
    window: int = knob(20, rule_int(1))  # J_c = mean cost of the last 20 finished training episodes (not in the paper)
    # lambda += lambda_lr * (J_c - cost_limit), clipped at 0 (not in the paper)
    lambda_lr: float = knob(0.01, POSITIVE)
    lambda_init: float = knob(0.0, rule_number(0))


@dataclass
class SacRsConfig:
    """SAC-RS: SAC (TorchRL's SACLoss) on the env's shaped reward (spec §4), no constraint."""

    method: str = knob("sac_rs", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))  # torch and the env's scene draws
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))  # paper | cpu (30K env steps) | smoke (CI, seconds)
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    collector: SacCollectorConfig = field(default_factory=SacCollectorConfig)
    replay_buffer: ReplayBufferConfig = field(default_factory=ReplayBufferConfig)
    optim: SacOptimConfig = field(default_factory=SacOptimConfig)
    loss: SacLossConfig = field(default_factory=SacLossConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


@dataclass
class SacLagConfig:
    """SAC-Lag: SAC plus a twin cost critic on the env's cost and a Lagrange multiplier
    (pe_rlhf.objectives.SACLagLoss): mean episode cost <= constraint.cost_limit."""

    method: str = knob("sac_lag", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    collector: SacCollectorConfig = field(default_factory=SacCollectorConfig)
    replay_buffer: ReplayBufferConfig = field(default_factory=ReplayBufferConfig)
    optim: SacOptimConfig = field(default_factory=SacOptimConfig)
    loss: SacLagLossConfig = field(default_factory=SacLagLossConfig)
    constraint: SacLagConstraintConfig = field(default_factory=SacLagConstraintConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


# --------------------------------------------------------------------------- PPO-RS, PPO-Lag, CPO


@dataclass
class PpoCollectorConfig:
    total_frames: int = knob(1_000_000, rule_int(1))  # the paper's budget for the RL baselines (Table 1: 1M env steps)
    frames_per_batch: int = knob(4000, rule_int(1))  # paper: "train batch size"


@dataclass
class PpoOptimConfig:
    lr: float = knob(5.0e-5, POSITIVE)  # paper
    epochs: int = knob(20, rule_int(1))  # paper: "number of SGD epochs" over each batch
    minibatch_size: int = knob(100, rule_int(1))  # paper: "SGD mini-batch size"
    max_grad_norm: Optional[float] = knob(None, GRAD_NORM)


@dataclass
class PpoLossConfig:
    """TorchRL ClipPPOLoss + RLlib's adaptive KL penalty (pe_rlhf.algorithms.baselines.algorithms.KLPenalty)."""

    gamma: float = knob(0.99, rule_number(0, 1))  # paper
    gae_lambda: float = knob(0.95, rule_number(0, 1))  # paper
    clip_epsilon: float = knob(0.2, POSITIVE)  # paper
    kl_coef: float = knob(0.2, rule_number(0))  # paper: "KL coefficient" (the penalty's initial weight)
    # RLlib's: the coefficient x1.5 above 2x, x0.5 below 1/2x this KL; null: fixed
    kl_target: Optional[float] = knob(0.01, rule_optional(POSITIVE))
    entropy_coef: float = knob(0.0, rule_number(0))  # not in the paper: RLlib's default (no entropy bonus)
    critic_coef: float = knob(1.0, rule_number(0))  # not in the paper: RLlib's vf_loss_coeff
    normalize_advantage: bool = knob(False, rule_bool)
    hidden: list[int] = knob([256, 256], rule_hidden)  # actor and critic(s) (not in the paper)


@dataclass
class PpoLagConstraintConfig(SacLagConstraintConfig):
    """lambda: one projected dual step per batch, before its epochs (paper: "cost limit for PPO-Lag")."""

    window: int = knob(10, rule_int(1))  # J_c = mean cost of the last 10 finished training episodes
    lambda_lr: float = knob(0.05, POSITIVE)


@dataclass
class PpoRsConfig:
    """PPO-RS: PPO (TorchRL's ClipPPOLoss, GAE) on the env's shaped reward (spec §4), no constraint."""

    method: str = knob("ppo_rs", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))
    # paper | cpu (32K env steps: whole batches of PE-RLHF's 30K budget) | smoke (CI, seconds)
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    collector: PpoCollectorConfig = field(default_factory=PpoCollectorConfig)
    optim: PpoOptimConfig = field(default_factory=PpoOptimConfig)
    loss: PpoLossConfig = field(default_factory=PpoLossConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


@dataclass
class PpoLagConfig:
    """PPO-Lag: PPO on the penalised advantage (A - lambda A_c) / (1 + lambda) with a cost value head
    (pe_rlhf.objectives.PPOLagLoss) and a Lagrange multiplier: mean episode cost <= constraint.cost_limit."""

    method: str = knob("ppo_lag", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    collector: PpoCollectorConfig = field(default_factory=PpoCollectorConfig)
    optim: PpoOptimConfig = field(default_factory=PpoOptimConfig)
    loss: PpoLossConfig = field(default_factory=PpoLossConfig)
    constraint: PpoLagConstraintConfig = field(default_factory=PpoLagConstraintConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


@dataclass
class CpoCollectorConfig(PpoCollectorConfig):
    frames_per_batch: int = knob(8000, rule_int(1))  # paper: "train batch size"


@dataclass
class CpoLossConfig:
    """CPOLoss; the CPO table's KL coefficient (0.2) and clip parameter (0.2) have no counterpart in CPO's update
    (the trust region is target_kl)."""

    gamma: float = knob(0.99, rule_number(0, 1))  # paper
    gae_lambda: float = knob(0.95, rule_number(0, 1))  # paper
    target_kl: float = knob(0.01, POSITIVE)  # the trust region (not in the paper; CPO's and OmniSafe's default)
    cg_iterations: int = knob(10, rule_int(1))
    cg_damping: float = knob(0.1, rule_number(0))
    backtrack_ratio: float = knob(0.8, rule_number(0, 1, lo_open=True, hi_open=True))
    max_backtracks: int = knob(15, rule_int(1))
    hidden: list[int] = knob([256, 256], rule_hidden)  # actor and value nets (not in the paper)


@dataclass
class CpoConstraintConfig:
    # paper: mean cost per episode (an episode here costs 0 or 1: see the module docstring)
    cost_limit: float = knob(1.0, rule_number(0))
    window: int = knob(10, rule_int(1))  # J_c = mean cost of the last 10 finished training episodes (not in the paper)


@dataclass
class CpoConfig:
    """CPO (Achiam et al. 2017; pe_rlhf.objectives.CPOLoss): per batch one constrained trust-region policy step
    (conjugate gradient, dual, recovery, line search), then the reward and cost value nets (``optim``: their
    regression; the policy moves by CPO's step only)."""

    method: str = knob("cpo", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    collector: CpoCollectorConfig = field(default_factory=CpoCollectorConfig)
    optim: PpoOptimConfig = field(default_factory=PpoOptimConfig)
    loss: CpoLossConfig = field(default_factory=CpoLossConfig)
    constraint: CpoConstraintConfig = field(default_factory=CpoConstraintConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


__all__ = ["ENV_DEFAULTS", "GRAD_NORM", "IMITATION_FAMILIES", "METHODS", "POSITIVE", "CheckpointConfig", "CpoConfig",
           "EvalConfig", "Method", "PpoCollectorConfig", "PpoLagConfig", "PpoLossConfig", "PpoOptimConfig",
           "PpoRsConfig", "SacLagConfig", "SacRsConfig"]
