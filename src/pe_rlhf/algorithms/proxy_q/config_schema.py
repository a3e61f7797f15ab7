"""The proxy-Q recipes' config (PE-RLHF, HACO, HAIM-DRL) as structured configs: the one place for every field's
default, type and rule.

:class:`RecipeConfig` holds one dataclass per group; each field is a :func:`~pe_rlhf.runtime.config_schema.knob` with
its default (the paper's values, spec §3), its declared type and its rule (:mod:`pe_rlhf.runtime.config_rules`, and
here the rules of these recipes' fields alone: what is allowed, in the words of the error). Hydra composes a recipe's
``config.yaml`` over it (:data:`PROXY_Q`, :mod:`pe_rlhf.runtime.config_compose`); :data:`RULES` (``{dotted field:
rule}``) and :func:`defaults` are derived from it.

Method: PE-RLHF = ``physics.enabled`` + ``selector.enabled``; HACO = both false (``recipes/haco``); HAIM-DRL =
HACO + ``disturbance.enabled`` (``recipes/haim_drl``).

The composed config is not type-checked by OmegaConf (its typed nodes would turn ``loss.cosine_cost=2`` into
``true`` and ``seed='5'`` into ``5``); the rules check every value, type included, after composition.
"""

from __future__ import annotations

import dataclasses
import importlib.util
from dataclasses import dataclass, field
from typing import Any, Optional

from pe_rlhf.modules.precision import PRECISIONS
from pe_rlhf.objectives.perlhf import FAILURE_TARGETS
from pe_rlhf.physics.safety import RECOVERIES
from pe_rlhf.runtime.config_compose import RecipeSchema
from pe_rlhf.runtime.config_rules import (SPLITS, Rule, rule_bool, rule_choice, rule_hidden, rule_int,
                                          rule_mentor_name, rule_number, rule_optional, rule_string,
                                          rule_target_entropy)
from pe_rlhf.runtime.config_schema import ActorSelectionConfig, LoggerConfig, knob, open_group
from pe_rlhf.algorithms.proxy_q.config_profiles import PROFILES

BACKENDS = ("single", "multisync", "multiasync", "ray")
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

    enabled: bool = knob(True, rule_bool)
    see_obstacles: bool = knob(False, rule_bool)  # true: IDM brakes for static obstacles and MOBIL passes them
    # IDM brakes for obstacles, MOBIL ignores them (stuck behind, as the paper describes); false: blind
    stop_for_obstacles: bool = knob(True, rule_bool)
    use_idm: bool = knob(True, rule_bool)  # false: "MOBIL only" ablation
    use_mobil: bool = knob(True, rule_bool)  # false: "IDM only" ablation


@dataclass
class SelectorConfig:
    """T_select: Q-ensemble value takeover (a_human vs a_phy)."""

    enabled: bool = knob(True, rule_bool)
    # forecast (seconds until a crash or off road, from the vehicle model: docs/results/claims) | expert (the
    # packaged SAC expert's critics) | expert:PATH (a Q-ensemble file or run folder) | warmup (fitted on the warm-up)
    value: str = knob("forecast", rule_value_source)
    # null: the value source's own (expert 1.5, the authors' code; warmup 0.5, the paper's table; forecast -0.5 s,
    # calibrated on train scenes: docs/results/claims); < 0: the mentor unless physics is valued -eps above
    epsilon_select: Optional[float] = knob(None, rule_optional(rule_number(meaning=EPSILON_SELECT_MEANING)))
    # the authors' code's escape (trust the mentor when std_k Q(s, a_phy) exceeds it)
    variance_threshold: Optional[float] = knob(None, rule_optional(rule_number(0)))
    # null: each step judged alone (paper); m: a takeover's choice switches only past eps -/+ m
    switch_margin: Optional[float] = knob(None, rule_optional(rule_number(0)))
    # physics replaces the mentor after this many consecutive vetoes in a takeover (1: every step judged alone)
    veto_patience: int = knob(1, rule_int(1))
    # with veto_patience > 1: a veto acts at once where the mentor's action fails within this many seconds
    imminent_failure: Optional[float] = knob(None, rule_optional(rule_number()))
    # selector.value=forecast: seconds each candidate action is held before the forecast's recovery
    forecast_hold: float = knob(1.0, rule_number(0, 3))
    # selector.value=forecast: the hold ends once the car has moved one lane width sideways (a lane change done)
    forecast_hold_one_lane: bool = knob(False, rule_bool)
    # selector.value=forecast: route (steer back along the route) | lanes (the best of the nearest lane's centre
    # and its neighbours')
    forecast_recovery: str = knob("route", rule_choice(*RECOVERIES))
    # the selector judges the mentor's warm-up too: true | auto (when selector.value needs no fit and the mentor
    # drives the warm-up) | false (the paper: the warm-up bypasses it; at seed 0 judging it cut the adversarial
    # run's training violations 68 -> 9 but the professional agent fell 0.54 -> 0.12: docs/results/claims)
    warmup_selection: Any = knob(False, lambda v: None if v == "auto" or isinstance(v, bool)
                                 else "allowed: auto, true, false")
    num_members: int = knob(5, rule_int(1))  # 1 = the "w/o ensemble" ablation
    hidden: list[int] = knob([256, 256], rule_hidden)
    warmup_fit_steps: int = knob(3000, rule_int(0))  # gradient steps fitting the ensemble once warm-up ends
    target_noise: float = knob(0.1, rule_number(0))  # sigma of a' = pi_expert(s') + N(0, sigma)
    # Polyak rate of the fit's target copy (not in the paper; see benchmarks/ensemble_fit_scale.py)
    tau: float = knob(0.005, rule_number(0, 1, lo_open=True))
    lr: float = knob(3.0e-4, _POSITIVE)
    batch_size: int = knob(256, rule_int(1))


@dataclass
class CollectorConfig:
    total_frames: int = knob(30000, rule_int(1))  # env steps of the whole run, warm-up included
    frames_per_batch: int = knob(100, rule_int(1))  # env steps per iteration
    warmup_steps: int = knob(10000, rule_int(0))  # the mentor drives alone; its data trains the Q-ensemble
    # a run folder (PE-RLHF/HACO or baseline): its trained actor drives the warm-up instead (expert-policy warm-up)
    warmup_policy: Optional[str] = knob(None, rule_optional(rule_string))
    learning_starts: int = knob(100, rule_int(0))
    # random: sample the policy while collecting | deterministic: propose its mode
    exploration: str = knob("random", rule_choice("random", "deterministic"))
    # loss.objective=proxy_value: sigma of the Gaussian noise added to the deterministic actor's proposal while
    # collecting (with exploration=random); 0: none (PVP)
    exploration_noise: float = knob(0.0, rule_number(0, 1))
    backend: str = knob("single", rule_backend)  # single | multisync | multiasync | ray
    num_workers: int = knob(1, rule_int(1))
    # env steps per second held by RealtimePacing (deadline clock); 0 = as fast as possible; mentor.name=human: 10
    # unless given
    realtime_hz: float = knob(0, rule_number(0))


@dataclass
class ReplayBufferConfig:
    size: int = knob(100000, rule_int(1))
    batch_size: int = knob(1024, rule_int(1))
    # null: one uniform buffer; a share s: takeover rows kept apart, up to s of every batch (authors' code: 0.5)
    takeover_share: Optional[float] = knob(None, rule_optional(rule_number(0, 1)))


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
class LossConfig:
    """The loss's arguments (+ tau for the target networks' SoftUpdate): PERLHFLoss (``objective=paper``) or
    ProxyValueLoss (``objective=proxy_value``); each reads its own fields below and the shared ones."""

    objective: str = knob("paper", rule_choice(*OBJECTIVES))  # paper (PERLHFLoss) | proxy_value (ProxyValueLoss)
    gamma: float = knob(0.99, rule_number(0, 1))
    tau: float = knob(0.005, rule_number(0, 1, lo_open=True))
    gap_coef: float = knob(10.0, rule_number(0))  # "CQL temperature"
    psi: float = knob(1.0, rule_number(0))
    intervention_weight: float = knob(1.0, rule_number(0))  # beta
    cosine_cost: bool = knob(True, rule_bool)  # false: the "w/o cosine takeover cost" ablation
    num_qvalue_nets: int = knob(2, rule_int(1))  # twin Q
    num_intervention_qvalue_nets: int = knob(1, rule_int(1))
    target_entropy: Any = knob("auto", rule_target_entropy)  # auto = -dim(A) = -2 (authors' code); the paper: 2.0
    alpha_init: float = knob(1.0, _POSITIVE)
    hidden: list[int] = knob([256, 256], rule_hidden)  # actor and critics
    disturbance_weight: float = knob(1.0, rule_number(0))  # actor's weight on Q_dist (with disturbance.enabled)
    num_disturbance_qvalue_nets: int = knob(2, rule_int(1))  # HAIM-DRL's twin disturbance critic
    # proxy-Q target of a crash/off-road end: zero (terminal 0) | bootstrap (as if it went on) | batch_min (the
    # batch's lowest)
    failure_target: str = knob("batch_min", rule_choice(*FAILURE_TARGETS))
    # evaluate the critics from their stacked parameters, each state's first-layer product once (same values up
    # to float summation order; false: through the modules)
    fused_critics: bool = knob(True, rule_bool)
    layer_norm: bool = knob(False, rule_bool)  # a LayerNorm after each hidden layer of the critics (RLPD, BRO)
    # objective=proxy_value: the label of the executed action (+B) and of the agent's proposal (-B) on takeover rows
    q_value_bound: float = knob(1.0, _POSITIVE)
    policy_delay: int = knob(2, rule_int(1))  # objective=proxy_value: an actor step every policy_delay critic steps
    target_noise: float = knob(0.2, rule_number(0))  # objective=proxy_value: TD3's target smoothing sigma
    target_noise_clip: float = knob(0.5, rule_number(0))  # ... clipped at this
    bc_weight: float = knob(0.0, rule_number(0))  # objective=proxy_value: behaviour cloning on takeover rows
    # objective=proxy_value: leave the rows where a takeover starts out of the TD term (PVP's mask)
    mask_td_at_takeover_start: bool = knob(False, rule_bool)
    # objective=proxy_value: false: takeover rows where physics was executed get TD only (no labels, no cloning)
    physics_labels: bool = knob(True, rule_bool)
    # objective=proxy_value: weight of the mean squared pre-tanh output in the actor's loss (keeps it unsaturated)
    preactivation_penalty: float = knob(0.0, rule_number(0))


@dataclass
class DisturbanceConfig:
    """HAIM-DRL's traffic-disturbance cost (pe_rlhf.transforms.TrafficDisturbanceCost)."""

    # true: the transform writes ("next", "disturbance_cost"), PERLHFLoss gets Q_dist
    enabled: bool = knob(False, rule_bool)
    threshold: float = knob(5.0, _POSITIVE)  # m/s^2: a step braking harder than this outside a takeover
    horizon: float = knob(3.0, _POSITIVE)  # s: IDM prediction of the followers' slowdown at the start of an event
    follower_range: float = knob(60.0, _POSITIVE)  # m behind the ego (its lane) within which vehicles count


@dataclass
class EvalConfig:
    every_frames: int = knob(5000, rule_int(0))  # 0: no periodic evaluation
    episodes: int = knob(10, rule_int(1))
    split: str = knob("test", rule_choice(*SPLITS))  # train | test
    video: bool = knob(True, rule_bool)


@dataclass
class CheckpointConfig:
    every_frames: int = knob(5000, rule_int(0))  # 0: no periodic checkpoints
    keep: int = knob(2, rule_int(1))  # most recent checkpoints kept on disk


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
    loss: LossConfig = field(default_factory=LossConfig)
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    actor_selection: ActorSelectionConfig = field(default_factory=ActorSelectionConfig)


def _fields(schema: type, prefix: str = ""):
    """``(dotted name, dataclasses.Field)`` of every leaf field and open group, in declaration order."""
    for f in dataclasses.fields(schema):
        if dataclasses.is_dataclass(f.type) or (isinstance(f.type, str) and f.type in _GROUPS):
            yield from _fields(_GROUPS[f.type] if isinstance(f.type, str) else f.type, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


_GROUPS = {cls.__name__: cls for cls in (MentorConfig, PhysicsSettings, SelectorConfig, CollectorConfig,
                                         ReplayBufferConfig, OptimConfig, LossConfig, DisturbanceConfig,
                                         LoggerConfig, EvalConfig, CheckpointConfig, ActorSelectionConfig)}

# {dotted field: rule}, every field but the open groups, in the schema's order.
RULES: dict[str, Rule] = {name: f.metadata["rule"] for name, f in _fields(RecipeConfig) if "rule" in f.metadata}


def defaults() -> dict[str, Any]:
    """The schema's defaults as a plain nested dict (a new copy each call)."""
    return dataclasses.asdict(RecipeConfig())


def default(key: str) -> Any:
    """The default of one dotted field (``optim.lr`` -> ``1e-4``)."""
    node: Any = defaults()
    for part in key.split("."):
        node = node[part]
    return node


SCHEMA = "pe_rlhf_schema"  # the structured config's name in Hydra's ConfigStore (recipes/pe_rlhf/config.yaml names it)
PROXY_Q = RecipeSchema(SCHEMA, defaults, PROFILES)  # PE-RLHF, HACO, HAIM-DRL


__all__ = ["BACKENDS", "PROXY_Q", "RULES", "SCHEMA", "RecipeConfig", "default", "defaults", "rule_backend",
           "rule_value_source"]
