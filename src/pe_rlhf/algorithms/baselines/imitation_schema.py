"""The imitation, offline and human-in-the-loop baselines' structured configs (BC, CQL, GAIL, HG-DAgger, IWR): the
one place for every field's default, type and rule, as :mod:`pe_rlhf.algorithms.baselines.config_schema` for the RL
baselines.

Families: ``offline`` (BC, CQL: gradient steps on recorded demonstrations, no env interaction; a metrics row every
``optim.updates_per_iteration`` updates, ``eval.every_updates`` / ``checkpoint.every_updates``), ``gail`` (the PPO
baselines' collector, optimiser and loss groups for the generator, a ``discriminator`` group) and ``hil``
(HG-DAgger, IWR: the simulated mentor takes over the agent during collection; ``collector.frames_per_batch`` env
steps a round, BC after each). Every one of them reads ``data`` (:mod:`pe_rlhf.algorithms.baselines.demos`): the
demonstrations, recorded by the recipe when missing. Values are the paper's appendix tables (BC, GAIL, HG-DAgger,
IWR, SAC/CQL) where they give one ("paper" beside a field); every other value says where it comes from.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from omegaconf import DictConfig

from pe_rlhf.algorithms.baselines.config_profiles import PROFILE_NAMES
from pe_rlhf.algorithms.baselines.config_schema import (
    ENV_DEFAULTS,
    GRAD_NORM,
    METHODS,
    POSITIVE,
    CheckpointConfig,
    EvalConfig,
    PpoCollectorConfig,
    PpoLossConfig,
    PpoOptimConfig,
)
from pe_rlhf.runtime.config_rules import (SPLITS, rule_choice, rule_hidden, rule_int, rule_mentor_name, rule_number,
                                          rule_optional, rule_string, rule_target_entropy)
from pe_rlhf.runtime.config_schema import LoggerConfig, knob, open_group


def _demo_mentor(v) -> str | None:
    if v == "human":
        return "record a person's demonstrations first (pe-rlhf demo record --mentor human) and give data.path"
    return rule_mentor_name(v)


def _hil_mentor(v) -> str | None:
    if v == "human":
        return ("a person in the loop needs the PE-RLHF recipe's real-time pacing; here: a simulated mentor "
                "or a 'package.module:ClassName' import path")
    return rule_mentor_name(v)


def _mapping(v) -> str | None:
    return None if isinstance(v, (dict, DictConfig)) else "must be a mapping of SkillProfile fields"


@dataclass
class DataConfig:
    """The demonstrations (pe_rlhf.algorithms.baselines.demos), recorded when missing."""

    # a dataset of `pe-rlhf demo record`; null: <run folder>/demos. Recorded (or extended) there when it holds
    # fewer than data.steps
    path: Optional[str] = knob(None, rule_optional(rule_string))
    # paper: dataset size 49,000 (the first data.steps transitions are used; CQL's table note says 50K)
    steps: int = knob(49_000, rule_int(1))
    # who drives when demonstrations are recorded (the paper: a person); any simulated mentor or import path
    mentor: str = knob("professional", _demo_mentor)


@dataclass
class OfflineEvalConfig:
    """Deterministic actions, no mentor; the final evaluation uses the same settings."""

    every_updates: int = knob(50_000, rule_int(0))  # 0: only the final evaluation
    episodes: int = knob(50, rule_int(1))  # the first N scenes of the split (the test split has 50)
    split: str = knob("test", rule_choice(*SPLITS))  # train | validation | test


@dataclass
class OfflineCheckpointConfig:
    every_updates: int = knob(50_000, rule_int(0))  # 0: only at the end
    keep: int = knob(2, rule_int(1))


@dataclass
class BCOptimConfig:
    updates: int = knob(200_000, rule_int(1))  # paper: "SGD epoch 200000", read as gradient steps (RLlib's BC)
    updates_per_iteration: int = knob(1_000, rule_int(1))  # gradient steps between metrics.csv rows (step = updates)
    batch_size: int = knob(32, rule_int(1))  # paper
    lr: float = knob(1.0e-4, POSITIVE)  # paper
    max_grad_norm: Optional[float] = knob(None, GRAD_NORM)  # null: no clipping


@dataclass
class BCLossConfig:
    # nll: -log pi(a|s) of the tanh-Gaussian actor (RLlib's BC) | mse: deterministic action vs label
    function: str = knob("nll", rule_choice("nll", "mse"))
    hidden: list[int] = knob([256, 256], rule_hidden)  # the actor (not in the paper; PE-RLHF's)


@dataclass
class BCConfig:
    """BC: behaviour cloning of recorded professional demonstrations (TorchRL's BCLoss), no env interaction."""

    method: str = knob("bc", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))  # torch, and the recording mentor's RNG when demonstrations are recorded
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))  # paper | cpu (20K demos, 50K updates) | smoke
    env: dict[str, Any] = open_group(ENV_DEFAULTS)  # the demonstrations are recorded on (and must match) this world
    data: DataConfig = field(default_factory=DataConfig)
    optim: BCOptimConfig = field(default_factory=BCOptimConfig)
    loss: BCLossConfig = field(default_factory=BCLossConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)  # log_every: iterations of updates_per_iteration
    eval: OfflineEvalConfig = field(default_factory=OfflineEvalConfig)
    checkpoint: OfflineCheckpointConfig = field(default_factory=OfflineCheckpointConfig)


@dataclass
class CQLOptimConfig(BCOptimConfig):
    updates: int = knob(100_000, rule_int(1))  # paper's text: CQL run for 50K and 100K iterations (no gain from 100K)
    batch_size: int = knob(256, rule_int(1))  # not in the paper: RLlib's CQL train batch


@dataclass
class CQLLossConfig:
    """TorchRL CQLLoss (twin Q: CQLLoss fixes 2, target networks by SoftUpdate, automatic entropy)."""

    gamma: float = knob(0.99, rule_number(0, 1))  # paper
    tau: float = knob(0.005, rule_number(0, 1, lo_open=True))  # paper
    temperature: float = knob(5.0, POSITIVE)  # paper: CQL loss temperature beta
    min_q_weight: float = knob(0.2, rule_number(0))  # paper: min Q weight multiplier
    # actor on the BC term first (RLlib's bc_iters). Not the paper's 200000, which exceeds its 50-100K iterations
    # and would leave the whole run BC; RLlib's default 20000
    bc_steps: int = knob(20_000, rule_int(0))
    num_random: int = knob(10, rule_int(1))  # random actions per state in the CQL term (not in the paper; RLlib's)
    target_entropy: Any = knob("auto", rule_target_entropy)  # auto = -dim(A) = -2
    alpha_init: float = knob(1.0, POSITIVE)
    hidden: list[int] = knob([256, 256], rule_hidden)  # actor and critics (not in the paper; PE-RLHF's)


@dataclass
class CQLConfig:
    """CQL: conservative Q-learning (TorchRL's CQLLoss) on recorded professional demonstrations and their env
    reward, no env interaction."""

    method: str = knob("cql", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))
    # paper | cpu (20K demos, 15K updates, 4 random actions) | smoke (CI, seconds)
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    data: DataConfig = field(default_factory=DataConfig)
    optim: CQLOptimConfig = field(default_factory=CQLOptimConfig)
    loss: CQLLossConfig = field(default_factory=CQLLossConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: OfflineEvalConfig = field(default_factory=OfflineEvalConfig)
    checkpoint: OfflineCheckpointConfig = field(default_factory=OfflineCheckpointConfig)


@dataclass
class GailCollectorConfig(PpoCollectorConfig):
    # total_frames: not in the paper (no budget given for GAIL): the RL baselines' 1M env steps
    frames_per_batch: int = knob(12_800, rule_int(1))  # paper: sample batch size


@dataclass
class GailOptimConfig(PpoOptimConfig):
    """The generator (PPO)."""

    lr: float = knob(1.0e-4, POSITIVE)  # paper: generator learning rate
    epochs: int = knob(5, rule_int(1))  # paper: generator optimization epoch
    minibatch_size: int = knob(64, rule_int(1))  # paper: SGD batch size


@dataclass
class DiscriminatorConfig:
    """D(s, a) = P(mentor's | s, a), TorchRL GAILLoss (binary cross-entropy)."""

    lr: float = knob(5.0e-3, POSITIVE)  # paper: discriminator learning rate
    # paper: "discriminator optimization epoch 2000", read as gradient steps per batch
    updates_per_batch: int = knob(2000, rule_int(1))
    batch_size: int = knob(64, rule_int(1))  # demonstration and policy steps per step (the paper's SGD batch)
    hidden: list[int] = knob([256, 256], rule_hidden)  # not in the paper
    grad_penalty: float = knob(0.0, rule_number(0))  # > 0: GAILLoss's gradient penalty weight (not in the paper)


@dataclass
class GailConfig:
    """GAIL: a PPO generator (the PPO baselines' learner and loss, the KL coefficient from the PPO table) on the
    reward -log(1 - D(s, a)) of a discriminator trained on recorded professional demonstrations against the
    policy's steps. The env reward is logged, never learned from."""

    method: str = knob("gail", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))  # torch, the env's scene draws, and the recording mentor's RNG
    # paper | cpu (20K demos, 32K env steps in 4000-step PPO batches) | smoke (CI, seconds)
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    data: DataConfig = field(default_factory=DataConfig)
    collector: GailCollectorConfig = field(default_factory=GailCollectorConfig)
    optim: GailOptimConfig = field(default_factory=GailOptimConfig)
    loss: PpoLossConfig = field(default_factory=PpoLossConfig)
    discriminator: DiscriminatorConfig = field(default_factory=DiscriminatorConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


@dataclass
class HilMentorConfig:
    """Who takes over during training (as the PE-RLHF recipe's mentor group)."""

    # professional | amateur | adversarial | bad, or "package.module:Name" (not human: no real-time pacing here)
    name: str = knob("professional", _hil_mentor)
    kwargs: dict[str, Any] = open_group({}, _mapping)  # SkillProfile fields (e.g. action_noise)


@dataclass
class HilDataConfig(DataConfig):
    """The warm-up demonstrations."""

    steps: int = knob(30_000, rule_int(1))  # paper: initializing dataset size


@dataclass
class HilCollectorConfig:
    total_frames: int = knob(50_000, rule_int(1))  # paper: 50K env steps (Table 1)
    frames_per_batch: int = knob(5_000, rule_int(1))  # paper: interactions per round


@dataclass
class HilOptimConfig:
    lr: float = knob(4.0e-4, POSITIVE)  # paper
    batch_size: int = knob(256, rule_int(1))  # paper: SGD batch size
    # paper: "number of data aggregation epoch", passes over the dataset after each round
    epochs: int = knob(4, rule_int(1))
    # passes over the demonstrations before the first round (not in the paper: ~6K steps, what BC needs here)
    pretrain_epochs: int = knob(50, rule_int(0))
    max_grad_norm: Optional[float] = knob(None, GRAD_NORM)


@dataclass
class HilEvalConfig(EvalConfig):
    every_frames: int = knob(10_000, rule_int(0))  # 0: only the final evaluation


@dataclass
class HilCheckpointConfig(CheckpointConfig):
    """Actor, optimiser, the aggregated dataset, takeover counters, RNG; ``--resume DIR`` continues."""

    every_frames: int = knob(10_000, rule_int(0))  # 0: only at the end


@dataclass
class HGDaggerConfig:
    """HG-DAgger (Kelly et al. 2019): the agent drives, the simulated mentor takes over when its rule says so;
    only the takeover steps (labelled with the mentor's action) join the dataset, and the actor is refitted by
    behaviour cloning on the whole aggregate after each round."""

    method: str = knob("hg_dagger", rule_choice(*METHODS))
    seed: int = knob(0, rule_int(0))  # torch, the env's scene draws, and the recording mentor's RNG
    profile: str = knob("paper", rule_choice(*PROFILE_NAMES))  # paper | cpu (30K env steps) | smoke (CI, seconds)
    env: dict[str, Any] = open_group(ENV_DEFAULTS)
    mentor: HilMentorConfig = field(default_factory=HilMentorConfig)
    data: HilDataConfig = field(default_factory=HilDataConfig)
    collector: HilCollectorConfig = field(default_factory=HilCollectorConfig)
    optim: HilOptimConfig = field(default_factory=HilOptimConfig)
    loss: BCLossConfig = field(default_factory=BCLossConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)  # log_every: rounds between rows
    eval: HilEvalConfig = field(default_factory=HilEvalConfig)
    checkpoint: HilCheckpointConfig = field(default_factory=HilCheckpointConfig)


@dataclass
class IWRConfig(HGDaggerConfig):
    """IWR (intervention weighted regression, Mandlekar et al. 2020): the agent drives, the simulated mentor takes
    over when its rule says so; every executed step joins the dataset (labelled with the executed action), and
    behaviour cloning after each round weights takeover and other samples to equal total weight. The paper's IWR
    table gives HG-DAgger's values."""

    method: str = knob("iwr", rule_choice(*METHODS))


__all__ = ["BCConfig", "CQLConfig", "GailConfig", "HGDaggerConfig", "IWRConfig"]
