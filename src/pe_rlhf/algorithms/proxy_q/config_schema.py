"""The proxy-Q recipes' config (PE-RLHF, HACO, HAIM-DRL) as structured configs: the one place for every field's
default, type and rule.

:class:`RecipeConfig` holds one dataclass per group; each field is a :func:`~pe_rlhf.runtime.config_schema.knob` with
its default (the paper's values, spec §3), its declared type and its rule (:mod:`pe_rlhf.runtime.config_rules`, and
here the rules of these recipes' fields alone: what is allowed, in the words of the error). Hydra composes a recipe's
``config.yaml`` over it (:data:`PROXY_Q`, :mod:`pe_rlhf.runtime.config_compose`); :data:`RULES` (``{dotted field:
rule}``) and :func:`defaults` are derived from it.

Method: PE-RLHF = ``physics.enabled`` (physics proposes, the selector picks); HACO = false (``recipes/haco``); HAIM-DRL =
HACO + ``disturbance.enabled`` (``recipes/haim_drl``).

The composed config is not type-checked by OmegaConf (its typed nodes would turn ``loss.cosine_cost=2`` into
``true`` and ``seed='5'`` into ``5``); the rules check every value, type included, after composition.
"""

from __future__ import annotations

import dataclasses
import importlib.util
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any, NamedTuple, Optional

from pe_rlhf.modules.precision import PRECISIONS
from pe_rlhf.objectives.perlhf import FAILURE_TARGETS
from pe_rlhf.objectives.proxy_value import PROXY_REDUCTIONS
from pe_rlhf.runtime.config_compose import RecipeSchema
from pe_rlhf.runtime.config_rules import (SPLITS, Rule, rule_bool, rule_choice, rule_hidden, rule_int,
                                          rule_mentor_name, rule_number, rule_optional, rule_string,
                                          rule_target_entropy)
from pe_rlhf.runtime.config_schema import ActorSelectionConfig, LoggerConfig, knob, open_group
from pe_rlhf.algorithms.proxy_q.config_profiles import PROFILES

BACKENDS = ("single", "multisync", "multiasync", "ray")
PHYSICS_MODELS = ("idm_mobil", "idm", "mobil")
PHYSICS_OBSTACLES = ("stop", "avoid", "blind")
# paper: PERLHFLoss (HACO's proxy-Q, as the paper); proxy_value: ProxyValueLoss (PVP's bounded proxy values)
OBJECTIVES = ("paper", "proxy_value")


def rule_value_source(v) -> str | None:
    from pe_rlhf.algorithms.proxy_q.value_expert import packaged_expert_path, parse_value_source

    try:
        _, path = parse_value_source(v)
    except ValueError as err:
        return str(err).split("; ", 1)[1]
    path = path if path is not None or v != "expert" else packaged_expert_path()
    if path is not None and not path.exists():
        return f"{str(path)!r} does not exist (a Q-ensemble file or a run folder)"
    return None


def rule_backend(v) -> str | None:
    if v not in BACKENDS:
        return f"allowed: {list(BACKENDS)}"
    if v == "ray" and importlib.util.find_spec("ray") is None:
        return "'ray' needs the ray package, which is not installed (pip install ray); use multisync or multiasync"
    return None


# HybridActionSelector keeps the mentor iff mean_k[Q_k(s, a_mentor) - Q_k(s, a_phy)] >= epsilon_select.
EPSILON_SELECT_MEANING = ("any sign, in the value source's units: > 0 the mentor must be valued that much above "
                          "physics, 0 the higher-valued action wins, < 0 physics vetoes the mentor only when valued "
                          "-epsilon_select above it")
_POSITIVE = rule_number(0, lo_open=True)


@dataclass
class MentorConfig:
    # professional | amateur | adversarial | bad | human, or "package.module:Name"
    name: str = knob("professional", rule_mentor_name)
    # passed to make_mentor: SkillProfile fields (e.g. action_noise) or HumanMentor args
    kwargs: dict[str, Any] = open_group({})


@dataclass
class PhysicsSettings:
    """The recipe's physics group, pi_phy: IDM (longitudinal) + MOBIL (lane changes), paper parameters (the policy's own
    parameters are :class:`pe_rlhf.physics.PhysicsConfig`)."""

    enabled: bool = knob(True, rule_bool)  # false: no physics and no selector (HACO, HAIM-DRL, PVP)
    # idm_mobil (the paper) | idm (the "IDM only" ablation: no lane change) | mobil (the "MOBIL only" ablation: cruise)
    model: str = knob("idm_mobil", rule_choice(*PHYSICS_MODELS))
    # stop: IDM brakes for static obstacles, MOBIL ignores them (stuck behind, as the paper describes) | avoid: IDM
    # brakes for them and MOBIL passes them | blind: neither sees them
    obstacles: str = knob("stop", rule_choice(*PHYSICS_OBSTACLES))


@dataclass
class SelectorConfig:
    """T_select: which of the mentor's and physics' actions a takeover executes (with ``physics.enabled``), by the
    physics forecast; ``selector.value=expert|warmup`` brings the Q-ensemble's setting."""

    # forecast (seconds until a crash or off road, from the vehicle model: docs/guide/shield.md) | expert (the
    # packaged SAC expert's critics) | expert:PATH (a Q-ensemble file or run folder) | warmup (a Q-ensemble fitted on
    # the warm-up, the paper's)
    value: str = knob("forecast", rule_value_source)
    # null: the value source's own (expert 1.5, the authors' code; warmup 0.5, the paper's table; forecast -0.5 s,
    # calibrated on train scenes: docs/results/claims); < 0: the mentor unless physics is valued -eps above
    epsilon_select: Optional[float] = knob(None, rule_optional(rule_number(meaning=EPSILON_SELECT_MEANING)))


@dataclass
class EnsembleSelectorConfig(SelectorConfig):
    """``selector.value=expert|expert:PATH|warmup``: the selector values the two actions with a Q-ensemble."""

    value: str = knob("warmup", rule_value_source)  # expert | expert:PATH | warmup (the paper's)
    num_members: int = knob(5, rule_int(1))  # the ensemble's members; 1 = the "w/o ensemble" ablation


def selector_variant(value: Any) -> str:
    """The selector's variant for ``selector.value``: ``forecast``, or ``q_ensemble`` (expert, expert:PATH, warmup);
    ValueError on a value that names neither."""
    from pe_rlhf.algorithms.proxy_q.value_expert import parse_value_source

    return "forecast" if parse_value_source(value)[0] == "forecast" else "q_ensemble"


@dataclass
class CollectorConfig:
    total_frames: int = knob(30000, rule_int(1))  # env steps of the whole run, warm-up included
    frames_per_batch: int = knob(100, rule_int(1))  # env steps per iteration
    warmup_steps: int = knob(10000, rule_int(0))  # the mentor drives alone; its data trains the Q-ensemble
    # a run folder (PE-RLHF/HACO or baseline): its trained actor drives the warm-up instead (expert-policy warm-up)
    warmup_policy: Optional[str] = knob(None, rule_optional(rule_string))
    # loss.objective=proxy_value: sigma of the Gaussian noise added to the deterministic actor's proposal while
    # collecting; 0: none (PVP). (loss.objective=paper samples its stochastic actor.)
    exploration_noise: float = knob(0.0, rule_number(0, 1))
    backend: str = knob("single", rule_backend)  # single | multisync | multiasync | ray
    num_workers: int = knob(1, rule_int(1))
    # env steps per second held by RealtimePacing (deadline clock); 0 = as fast as possible; mentor.name=human: 10
    # unless given
    realtime_hz: float = knob(0, rule_number(0))


@dataclass
class ReplayBufferConfig:
    size: int = knob(100000, rule_int(1))
    # PE-RLHF's 128 with the proxy values (PVP's batch; calibrated on train scenes: docs/experiments/learner.md); the
    # paper's loss 1024 (its appendix; recipes/haco)
    batch_size: int = knob(128, rule_int(1))
    # null: one uniform buffer; a share s: takeover rows kept apart, up to s of every batch (authors' code and PVP: 0.5)
    takeover_share: Optional[float] = knob(0.5, rule_optional(rule_number(0, 1)))


@dataclass
class OptimConfig:
    lr: float = knob(1.0e-4, _POSITIVE)
    updates_per_batch: int = knob(100, rule_int(1))  # one gradient step per env step, as the paper
    max_grad_norm: Optional[float] = knob(10.0, rule_optional(_POSITIVE))  # null: no clipping
    # true: updates run in a learner thread beside acting (same update-to-data ratio); mentor.name=human: true
    # unless given
    async_updates: bool = knob(False, rule_bool)
    # the updates' intra-op threads: auto = the cores other processes leave free, re-checked every batch
    # (pe_rlhf.threads.FreeCores) | an int
    threads: Any = knob("auto", lambda v: None if v == "auto" or (isinstance(v, int) and not isinstance(v, bool)
                                                                   and v >= 1) else "allowed: auto, or an int >= 1")
    # where the networks and updates run: auto (CUDA if torch sees one) | cpu | cuda | cuda:N; acting stays on the
    # CPU (a copy synced after each round)
    device: str = knob("auto", lambda v: None if isinstance(v, str) and _is_device(v)
                       else "allowed: auto, cpu, cuda, cuda:N")
    # fp32 | bf16: bf16 autocast in the updates, fp32 weights and outputs (pe_rlhf.modules.precision)
    precision: str = knob("fp32", rule_choice(*PRECISIONS))


def _is_device(v: str) -> bool:
    return v in ("auto", "cpu", "cuda") or (v.startswith("cuda:") and v[5:].isdigit())


@dataclass
class LossCommon:
    """What both losses read (+ tau for the target networks' SoftUpdate); ``objective`` picks the loss and with it the
    group's other settings (:data:`LOSSES`)."""

    objective: str = knob("paper", rule_choice(*OBJECTIVES))  # paper (PERLHFLoss) | proxy_value (ProxyValueLoss)
    gamma: float = knob(0.99, rule_number(0, 1))
    tau: float = knob(0.005, rule_number(0, 1, lo_open=True))
    hidden: list[int] = knob([256, 256], rule_hidden)  # actor and critics (and a fitted selector ensemble's members)
    layer_norm: bool = knob(False, rule_bool)  # a LayerNorm after each hidden layer of the critics (RLPD, BRO)


@dataclass
class PaperLossConfig(LossCommon):
    """``loss.objective=paper``: PERLHFLoss, HACO's proxy-Q loss as the paper (spec §3)."""

    num_qvalue_nets: int = knob(2, rule_int(1))  # twin Q
    gap_coef: float = knob(10.0, rule_number(0))  # "CQL temperature"
    psi: float = knob(1.0, rule_number(0))
    intervention_weight: float = knob(1.0, rule_number(0))  # beta
    cosine_cost: bool = knob(True, rule_bool)  # false: the "w/o cosine takeover cost" ablation
    num_intervention_qvalue_nets: int = knob(1, rule_int(1))
    target_entropy: Any = knob("auto", rule_target_entropy)  # auto = -dim(A) = -2 (authors' code); the paper: 2.0
    alpha_init: float = knob(1.0, _POSITIVE)
    # proxy-Q target of a crash/off-road end: zero (terminal 0) | bootstrap (as if it went on) | batch_min (the
    # batch's lowest)
    failure_target: str = knob("batch_min", rule_choice(*FAILURE_TARGETS))


@dataclass
class ProxyValueLossConfig(LossCommon):
    """``loss.objective=proxy_value``: ProxyValueLoss, PVP's bounded proxy values (TD3: twin critics, a deterministic
    actor)."""

    objective: str = knob("proxy_value", rule_choice(*OBJECTIVES))  # paper (PERLHFLoss) | proxy_value (ProxyValueLoss)
    # the label of the executed action (+B) and of the agent's proposal (-B) on takeover rows
    q_value_bound: float = knob(1.0, _POSITIVE)
    policy_delay: int = knob(2, rule_int(1))  # an actor step every policy_delay critic steps
    target_noise: float = knob(0.2, rule_number(0))  # TD3's target smoothing sigma (clipped at 2.5 sigma, TD3's 0.5)
    bc_weight: float = knob(0.0, rule_number(0))  # behaviour cloning on takeover rows (PVP4Real)
    mask_td_at_takeover_start: bool = knob(False, rule_bool)  # leave the rows where a takeover starts out of TD (PVP)
    # takeover_rows: the proxy labels on takeover rows | batch: PVP's released code (over the whole batch, times the
    # takeover share, so agent rows are pulled to 0; TD weighted 0.5)
    proxy_reduction: str = knob("takeover_rows", rule_choice(*PROXY_REDUCTIONS))


# loss.objective -> its group's settings
LOSSES: dict[str, type] = {"paper": PaperLossConfig, "proxy_value": ProxyValueLossConfig}


@dataclass
class DisturbanceOff:
    """``disturbance.enabled=false`` (PE-RLHF, HACO, PVP): the group's one setting."""

    # true: HAIM-DRL's traffic-disturbance cost and critic (the group's other settings appear)
    enabled: bool = knob(False, rule_bool)


@dataclass
class DisturbanceConfig:
    """``disturbance.enabled=true``: HAIM-DRL's traffic-disturbance cost (pe_rlhf.transforms.TrafficDisturbanceCost)
    and PERLHFLoss's disturbance critic Q_dist."""

    # the transform writes ("next", "disturbance_cost"), PERLHFLoss gets Q_dist
    enabled: bool = knob(True, rule_bool)
    threshold: float = knob(5.0, _POSITIVE)  # m/s^2: a step braking harder than this outside a takeover
    horizon: float = knob(3.0, _POSITIVE)  # s: IDM prediction of the followers' slowdown at the start of an event
    follower_range: float = knob(60.0, _POSITIVE)  # m behind the ego (its lane) within which vehicles count
    weight: float = knob(1.0, rule_number(0))  # the actor's weight on Q_dist
    num_qvalue_nets: int = knob(2, rule_int(1))  # the twin disturbance critic


# disturbance.enabled -> its group's settings
DISTURBANCES: dict[bool, type] = {False: DisturbanceOff, True: DisturbanceConfig}


@dataclass
class EvalConfig:
    every_frames: int = knob(5000, rule_int(0))  # 0: no periodic evaluation
    episodes: int = knob(10, rule_int(1))
    split: str = knob("test", rule_choice(*SPLITS))  # train | validation | test
    video: bool = knob(True, rule_bool)


@dataclass
class CheckpointConfig:
    every_frames: int = knob(5000, rule_int(0))  # 0: no periodic checkpoints
    keep: int = knob(2, rule_int(1))  # most recent checkpoints kept on disk


@dataclass
class PickedActorConfig(ActorSelectionConfig):
    """Picking the run's actor on train scenes (:mod:`pe_rlhf.runtime.actor_selection`): PE-RLHF keeps the best of its
    5K-frame snapshots (train scenes 0-49), since a seed can lose late what it had learned (docs/experiments/learner.md:
    picked on train scenes 0-24, on 25-49 the picked actors scored 0.64 / 0.60 / 0.52 against the last ones' 0.64 /
    0.52 / 0.20, seeds 0-2)."""

    every_frames: int = knob(5000, rule_int(0))  # 0: the last actor is the run's actor


@dataclass
class RecipeConfig:
    """The proxy-Q recipes' config: the paper's values (spec §3, the appendix hyper-parameter table)."""

    seed: int = knob(0, rule_int(0))
    profile: str = knob("paper", rule_choice(*PROFILES))  # paper | cpu | quick | smoke (config_profiles.PROFILES)
    # Any pe_rlhf.envs.config.DrivingConfig field (traffic_density, horizon, lanes, ...); unset fields keep
    # DrivingConfig's defaults, and split defaults to train (eval uses eval.split). lane_features: the lane summary
    # beside the lidar (pe_rlhf.envs.observation): every Table-1 row uses it.
    env: dict[str, Any] = open_group({"lane_features": True})
    mentor: MentorConfig = field(default_factory=MentorConfig)
    physics: PhysicsSettings = field(default_factory=PhysicsSettings)
    selector: SelectorConfig = field(default_factory=SelectorConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    replay_buffer: ReplayBufferConfig = field(default_factory=ReplayBufferConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    # the settings of loss.objective's loss (LOSSES): proxy_value (ProxyValueLoss) or paper (PERLHFLoss)
    loss: ProxyValueLossConfig = field(default_factory=ProxyValueLossConfig)
    disturbance: DisturbanceOff = field(default_factory=DisturbanceOff)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    actor_selection: PickedActorConfig = field(default_factory=PickedActorConfig)


def _fields(schema: type, prefix: str = ""):
    """``(dotted name, dataclasses.Field)`` of every leaf field and open group, in declaration order."""
    for f in dataclasses.fields(schema):
        if dataclasses.is_dataclass(f.type) or (isinstance(f.type, str) and f.type in _GROUPS):
            yield from _fields(_GROUPS[f.type] if isinstance(f.type, str) else f.type, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


_GROUPS = {cls.__name__: cls for cls in (MentorConfig, PhysicsSettings, SelectorConfig, EnsembleSelectorConfig,
                                         CollectorConfig,
                                         ReplayBufferConfig, OptimConfig, PaperLossConfig, ProxyValueLossConfig,
                                         DisturbanceOff, DisturbanceConfig, LoggerConfig, EvalConfig,
                                         CheckpointConfig, ActorSelectionConfig, PickedActorConfig)}

class VariantGroup(NamedTuple):
    """A group whose settings depend on one of its fields: ``field``, ``classes`` (``{variant: the group's
    dataclass}``) and ``pick`` (the variant a value of ``field`` selects; ValueError on a bad one)."""

    field: str
    classes: dict[Any, type]
    pick: Callable[[Any], Any] = lambda value: value


# A config shows the chosen variant's settings only; the schema's (and Hydra's) node for these groups is open, and
# pe_rlhf.algorithms.proxy_q.config.complete_variants completes and checks it after composition.
VARIANTS: dict[str, VariantGroup] = {
    "selector": VariantGroup("value", {"forecast": SelectorConfig, "q_ensemble": EnsembleSelectorConfig},
                             selector_variant),
    "loss": VariantGroup("objective", LOSSES),
    "disturbance": VariantGroup("enabled", DISTURBANCES),
}

# {dotted field: rule}, every field but the open groups and the variant groups', in the schema's order.
RULES: dict[str, Rule] = {name: f.metadata["rule"] for name, f in _fields(RecipeConfig)
                          if "rule" in f.metadata and name.split(".", 1)[0] not in VARIANTS}


def variant_rules(group: str, variant: Any) -> dict[str, Rule]:
    """``{dotted field: rule}`` of ``group``'s ``variant`` (``variant_rules("loss", "proxy_value")``)."""
    return {name: f.metadata["rule"] for name, f in _fields(VARIANTS[group].classes[variant], f"{group}.")}


def variant_defaults(group: str, variant: Any) -> dict[str, Any]:
    """The defaults of ``group``'s ``variant`` as a plain dict (a new copy each call)."""
    return dataclasses.asdict(VARIANTS[group].classes[variant]())


def defaults() -> dict[str, Any]:
    """The schema's defaults as a plain nested dict (a new copy each call): each variant group at its default
    variant (``selector.value=forecast``, ``loss.objective=proxy_value``, ``disturbance.enabled=false``)."""
    return dataclasses.asdict(RecipeConfig())


def default(key: str) -> Any:
    """The default of one dotted field (``optim.lr`` -> ``1e-4``); a variant group's field that the default variant
    lacks has its own variant's default (``loss.q_value_bound`` -> ``1.0``)."""
    group, _, rest = key.partition(".")
    if group in VARIANTS:
        for variant in VARIANTS[group].classes:
            values = variant_defaults(group, variant)
            if rest in values:
                return values[rest]
        raise KeyError(key)
    node: Any = defaults()
    for part in key.split("."):
        node = node[part]
    return node


SCHEMA = "pe_rlhf_schema"  # the structured config's name in Hydra's ConfigStore (recipes/pe_rlhf/config.yaml names it)
# PE-RLHF, HACO, HAIM-DRL, PVP; the variant groups are open in Hydra's node (each file brings its variant's settings)
PROXY_Q = RecipeSchema(SCHEMA, defaults, PROFILES, variant_groups=tuple(VARIANTS))


__all__ = ["BACKENDS", "DISTURBANCES", "LOSSES", "PROXY_Q", "RULES", "SCHEMA", "VARIANTS", "RecipeConfig",
           "VariantGroup",
           "default", "defaults", "rule_backend", "rule_value_source", "selector_variant", "variant_defaults",
           "variant_rules"]
