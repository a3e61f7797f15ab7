"""Builders shared by the recipes: env with interventions, collector, replay buffer, loss, optimisers.

Each takes the recipe config (an OmegaConf ``DictConfig`` validated by
:func:`pe_rlhf.algorithms.proxy_q.config.validate_config`) and returns a ready TorchRL object,
as TorchRL's ``sota-implementations/*/utils.py`` do.

Collection backends (``collector.backend``), all TorchRL collectors:

- ``single``: :class:`~torchrl.collectors.Collector` over the env this process built;
- ``multisync``: :class:`~torchrl.collectors.MultiSyncCollector`, ``collector.num_workers`` processes,
  each collecting ``frames_per_batch / num_workers`` steps of every batch (stacked ``(N, T / N)``);
- ``multiasync``: :class:`~torchrl.collectors.MultiAsyncCollector`, each batch is one worker's
  ``frames_per_batch`` steps (``(T,)``), whichever finished first; workers keep collecting while the
  main process trains, so a batch can straddle a policy or ensemble update;
- ``ray``: :class:`~torchrl.collectors.distributed.RayCollector` (``pip install pe-rlhf[ray]``), sync
  mode, same layout as ``multisync``.

Worker ``i`` builds its own env with :func:`make_worker_env` (its own mentor, physics, selector,
``InterventionTransform`` and, with ``disturbance.enabled`` (HAIM-DRL), ``TrafficDisturbanceCost``): env
seed ``seed + i``, mentor seed ``seed + i``, warm-up ``ceil(collector.warmup_steps / num_workers)``
steps. The Q-ensemble reaches the workers in shared
memory (``share_memory()``; handed over through ``create_env_kwargs``, which torch.multiprocessing
pickles with storage handles), so the main process's in-place fits are seen at once; ray workers
cannot share memory and get the weights from :func:`push_value_source_weights`. Policy weights reach
the workers at :func:`sync_policy`.
"""

from __future__ import annotations

import functools
import math

import torch
from torchrl.collectors import BaseCollector, Collector, MultiAsyncCollector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType
from torchrl.objectives import SoftUpdate

from pe_rlhf.envs.torchrl_env import make_env
from pe_rlhf.mentors import Mentor
from pe_rlhf.modules import QEnsemble
from pe_rlhf.objectives import PERLHFLoss, make_adam
from pe_rlhf.physics import IDMMobilPolicy, SafetyForecastConfig, SafetyForecastValue
from pe_rlhf.runtime.world import build_mentor, obs_dim
from pe_rlhf.threads import thread_budget
from pe_rlhf.algorithms.proxy_q.model_builders import build_actor, build_loss, uses_proxy_values  # noqa: F401
from pe_rlhf.algorithms.proxy_q.takeover_replay import TakeoverBalancedReplayBuffer
from pe_rlhf.algorithms.proxy_q.value_expert import load_value_expert, parse_value_source
from pe_rlhf.transforms import (
    LATCH_RELEASE_SPEED,
    HybridActionSelector,
    InterventionTransform,
    RealtimePacing,
    TrafficDisturbanceCost,
)

# The default world's observation (240 lidar beams); obs_dim(cfg) follows env.lidar_beams and env.lane_features.
OBS_DIM = 250
# What the selector values actions with: a Q-ensemble (fitted on the warm-up, or the packaged expert) or the physics
# forecast (seconds until a failure).
ValueSource = QEnsemble | SafetyForecastValue
# A worker's Q-ensemble seen from its collector, in TorchRL's attribute-path notation (cascade_execute);
# make_worker_env checks that the InterventionTransform is the env's last transform when there is a selector.
# (HAIM-DRL's TrafficDisturbanceCost comes after it, and HAIM-DRL has no selector.)
WORKER_ENSEMBLE_PATH = "env.transform[-1].selector.q_ensemble"


def build_warmup_driver(cfg):
    """Who drives the warm-up instead of the mentor (``collector.warmup_policy``): None (the mentor: the
    demonstration warm-up), or a :class:`~pe_rlhf.evaluation.TorchRLPolicyAdapter` over the trained actor of
    that run folder, PE-RLHF/HACO or baseline (the expert-policy warm-up). Raises ``ConfigError`` naming the
    field when the folder holds no finished run or its actor reads another observation width."""
    path = cfg.collector.warmup_policy
    if path is None:
        return None
    from pe_rlhf.evaluation import TorchRLPolicyAdapter
    from pe_rlhf.runtime.config_rules import ConfigError
    from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor, run_observation_size

    field = "collector.warmup_policy"
    try:
        width = run_observation_size(path)
        actor = load_run_actor(path)
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"{field}={path!r}: {e}", field) from None
    if width != obs_dim(cfg):
        raise ConfigError(f"{field}={path!r}: its actor reads {width}-float observations, this run's env gives "
                          f"{obs_dim(cfg)} (env.lane_features / env.lidar_beams differ)", field)
    return TorchRLPolicyAdapter(actor)


def build_physics(cfg) -> IDMMobilPolicy | None:
    from pe_rlhf.algorithms.proxy_q.config import physics_config

    return IDMMobilPolicy(physics_config(cfg)) if cfg.physics.enabled else None


def value_is_fitted(cfg) -> bool:
    """Whether the selector's ensemble is fitted on the warm-up (``selector.value=warmup``) rather than a
    frozen expert's critics."""
    return parse_value_source(cfg.selector.value)[0] == "warmup"


def build_value_source(cfg) -> ValueSource | None:
    """The selector's value estimator: a fresh ensemble to fit on the warm-up, or the frozen expert that
    ``selector.value`` names (at most ``selector.num_members`` of its members), the physics forecast
    (``forecast``: seconds until a failure, nothing to fit), or None without physics (HACO, HAIM-DRL, PVP). The
    fitted ensemble's members have the loss's hidden sizes."""
    if not cfg.physics.enabled:
        return None
    kind, path = parse_value_source(cfg.selector.value)
    if kind == "forecast":
        return SafetyForecastValue(SafetyForecastConfig())
    if kind == "expert":
        return load_value_expert(path, obs_dim(cfg), max_members=int(cfg.selector.num_members))
    return QEnsemble(obs_dim(cfg), num_members=int(cfg.selector.num_members), hidden=tuple(cfg.loss.hidden))


# The warm-up ensemble's fit (selector.value=warmup), at the paper's values: 0.3 gradient steps per warm-up step (3000
# after its 10K), batch 256, Adam at 3e-4, target smoothing sigma 0.1 (a' = pi_expert(s') + N(0, sigma)) and a Polyak
# rate of 0.005 for the fit's target copy (not in the paper; benchmarks/ensemble_fit_scale.py).
ENSEMBLE_FIT = {"steps_per_warmup_step": 0.3, "batch_size": 256, "lr": 3.0e-4, "target_noise": 0.1, "tau": 0.005}


def ensemble_fit_steps(cfg) -> int:
    """Gradient steps fitting the ensemble once the warm-up ends (0: nothing is fitted: a forecast or an expert)."""
    if not cfg.physics.enabled or not value_is_fitted(cfg):
        return 0
    return max(1, math.ceil(ENSEMBLE_FIT["steps_per_warmup_step"] * int(cfg.collector.warmup_steps)))


# selector.epsilon_select=null takes the value source's own threshold, in that source's units: the expert's as in the
# authors' code; the warm-up ensemble's as in the paper's table; the forecast's in seconds, calibrated on train scenes
# 0-9 (docs/results/claims/README.md: -0.5 kept the professional's 1.00 and held the adversarial floor).
EPSILON_BY_VALUE = {"expert": 1.5, "warmup": 0.5, "forecast": -0.5}


def epsilon_select(cfg) -> float:
    """``selector.epsilon_select``, or the default of ``selector.value``'s kind (:data:`EPSILON_BY_VALUE`) when null."""
    if cfg.selector.epsilon_select is not None:
        return float(cfg.selector.epsilon_select)
    return EPSILON_BY_VALUE[parse_value_source(cfg.selector.value)[0]]


# The rule over selector.value=forecast (HybridActionSelector's arguments): the executed-action floor held against the
# presets and the persistent adversaries on train scenes 0-9 with it (docs/experiments/shield-calibration.md, issue
# 42). A veto holds until the mentor's action repeated is no worse (latch); the mentor is compared with the better of
# physics' action and braking at once, and the better one runs (physics_or_recovery); no slack where that fallback
# itself fails (strict); where physics is safe, the mentor's action must make physics' progress less 1 m (a safe
# action can stop the car); a standing car's step is judged alone (the latch held the professional, steering around
# an obstacle at walking pace, behind it for the rest of the episode).
FORECAST_RULE = {"persistence": "latch", "reference": "physics_or_recovery", "strict_in_danger": True,
                 "progress_margin": 1.0, "latch_release_speed": LATCH_RELEASE_SPEED}


def build_selector(cfg, value_source: ValueSource) -> HybridActionSelector:
    """The recipe's ``HybridActionSelector`` over ``value_source`` at :func:`epsilon_select`; with
    ``selector.value=forecast`` also :data:`FORECAST_RULE` (the Q-ensemble sources keep the paper's rule: each step
    judged alone)."""
    rule = FORECAST_RULE if parse_value_source(cfg.selector.value)[0] == "forecast" else {}
    return HybridActionSelector(value_source, epsilon_select(cfg), **rule)


def build_train_env(cfg, env_config, mentor: Mentor, value_source: ValueSource | None, physics,
                    worker_index: int = 0, num_workers: int = 1):
    """The TorchRL driving env with ``InterventionTransform`` (PE-RLHF with a selector, HACO without), then
    ``TrafficDisturbanceCost`` with ``disturbance.enabled`` (HAIM-DRL; after it: it reads the takeover flag).

    As worker ``worker_index`` of ``num_workers``: seeded ``seed + worker_index``, with its share
    ``ceil(collector.warmup_steps / num_workers)`` of the warm-up.
    """
    env = make_env(env_config)
    selector = None
    if value_source is not None:
        selector = build_selector(cfg, value_source)
    warmup_steps = math.ceil(int(cfg.collector.warmup_steps) / num_workers)
    env.append_transform(InterventionTransform(mentor, selector, physics if selector else None,
                                               warmup_steps=warmup_steps, warmup_driver=build_warmup_driver(cfg)))
    if cfg.disturbance.enabled:
        d = cfg.disturbance
        env.append_transform(TrafficDisturbanceCost(float(d.threshold), float(d.horizon), float(d.follower_range)))
    if float(cfg.collector.realtime_hz) > 0:  # last: it ticks before the mentor is asked (see RealtimePacing)
        env.append_transform(RealtimePacing(float(cfg.collector.realtime_hz)))
    env.set_seed(int(cfg.seed) + int(worker_index))
    return env


def build_local_env(cfg, env_config, value_source: ValueSource | None):
    """``(env, mentor)`` of this process for the ``single`` backend; ``(None, None)`` for the
    multi-worker backends, whose workers build their own (:func:`make_worker_env`)."""
    if str(cfg.collector.backend) != "single":
        return None, None
    mentor = build_mentor(cfg)
    return build_train_env(cfg, env_config, mentor, value_source, build_physics(cfg)), mentor


def make_worker_env(cfg, worker_index: int, num_workers: int, start_frames: int = 0,
                    value_source: ValueSource | None = None):
    """Collector worker ``worker_index``'s env: its own mentor, physics, selector over ``ensemble``.

    A top-level function, so ``functools.partial(make_worker_env, cfg, ...)`` pickles into a worker.
    ``start_frames`` (a resumed run's global frame count) sets the transform's step counter to this
    worker's share, so a resumed run does not repeat the warm-up.
    """
    from pe_rlhf.runtime.config import driving_config

    env = build_train_env(cfg, driving_config(cfg), build_mentor(cfg, worker_index), value_source, build_physics(cfg),
                          worker_index, num_workers)
    transform = env.transform[-1] if value_source is not None else find_transform(env, InterventionTransform)
    if not isinstance(transform, InterventionTransform):
        raise TypeError(f"a worker env must end with its InterventionTransform (WORKER_ENSEMBLE_PATH), "
                           f"got {type(transform).__name__}")
    transform.total_steps = int(start_frames) // num_workers
    return env


def exploration_type(cfg) -> ExplorationType:
    """How the agent proposes actions while collecting: sampled (the paper loss's TanhNormal policy, SAC's usual
    collection; the proxy-value loss's deterministic actor is its own sample, plus ``collector.exploration_noise``)."""
    return ExplorationType.RANDOM


def build_collector(cfg, env, actor, total_frames: int | None = None, *, value_source: ValueSource | None = None,
                    start_frames: int = 0) -> BaseCollector:
    """The ``collector.backend`` collector (see the module docstring) of ``total_frames`` frames.

    ``single``: over ``env`` (this process's). Multi-worker backends: ``env`` must be None; each
    worker builds its own (:func:`make_worker_env`, with ``ensemble`` and ``start_frames``), and
    ``ensemble`` is moved to shared memory. Batches: ``(T,)``, or ``(N, T / N)`` for ``multisync``
    and ``ray`` (time last; flatten with ``reshape(-1)`` for a replay buffer).
    """
    backend, n = str(cfg.collector.backend), int(cfg.collector.num_workers)
    frames = int(cfg.collector.total_frames) if total_frames is None else int(total_frames)
    frames_per_batch = int(cfg.collector.frames_per_batch)
    explore = {"exploration_type": exploration_type(cfg)}
    if backend == "single":
        return Collector(env, actor, frames_per_batch=frames_per_batch, total_frames=frames, **explore)
    if env is not None:
        raise ValueError(f"collector.backend={backend}: the workers build their envs; pass env=None")
    factories = [functools.partial(make_worker_env, cfg, worker_index=i, num_workers=n, start_frames=start_frames)
                 for i in range(n)]
    if backend == "ray":
        from torchrl.collectors.distributed import RayCollector

        return RayCollector(**ray_collector_kwargs(cfg, factories, actor, frames, value_source))
    if value_source is not None:
        value_source.share_memory()
    collector_class = MultiSyncCollector if backend == "multisync" else MultiAsyncCollector
    extra = {"cat_results": "stack"} if backend == "multisync" else {}
    # num_threads: keep this process's thread count (TorchRL would lower it by the number of workers).
    return collector_class(factories, actor, frames_per_batch=frames_per_batch, total_frames=frames,
                           create_env_kwargs=[{"value_source": value_source}] * n, num_threads=torch.get_num_threads(),
                           **explore, **extra)


def batches_on_grid(collector: BaseCollector, frames: int):
    """``collector``'s batches, the first one sized to end on the ``frames_per_batch`` grid when the run's frame
    count ``frames`` is off it (a resume after a pending batch or from a checkpoint cut at ``total_frames``), so
    that the run's rows and updates land on the frames an uninterrupted run's do. Only the ``single`` backend's
    collector can size a batch; the multi-worker ones yield theirs as they come."""
    full = int(collector.frames_per_batch) if isinstance(collector, Collector) else 0
    first = full - frames % full if full else 0
    if not first or first == full:
        yield from collector
        return
    # TorchRL's Collector steps ``frames_per_batch`` times into its preallocated ``_final_rollout``: a view of its
    # first ``first`` steps makes one short batch; both are put back before the next batch is collected.
    buffer = getattr(collector, "_final_rollout", None)
    collector.frames_per_batch = first
    if buffer is not None:
        collector._final_rollout = buffer[..., :first]
    for i, batch in enumerate(collector):
        yield batch
        if i == 0:
            collector.frames_per_batch = full
            if buffer is not None:
                collector._final_rollout = buffer


def ray_collector_kwargs(cfg, factories: list, actor, total_frames: int, value_source: ValueSource | None) -> dict:
    """``RayCollector`` arguments: one ``Collector`` per worker, sync (batches ``(N, T / N)``). The
    ensemble travels by value in each factory (no shared memory): :func:`push_value_source_weights`."""
    return {"create_env_fn": [functools.partial(f, value_source=value_source) for f in factories], "policy": actor,
            "frames_per_batch": int(cfg.collector.frames_per_batch), "total_frames": int(total_frames),
            "collector_class": Collector, "num_collectors": len(factories), "sync": True,
            "collector_kwargs": {"exploration_type": exploration_type(cfg)}}


def sync_policy(collector: BaseCollector) -> None:
    """Send the actor's current weights to the collector's workers (a no-op for ``single``, whose
    collector runs this process's actor). With multisync/multiasync TorchRL's default
    ``SharedMemWeightSyncScheme`` already puts the actor's parameters in shared memory (measured: workers
    act with in-place updates even before this call); the call is the scheme's hand-over all the same,
    and what ray workers need."""
    if not isinstance(collector, Collector):
        collector.update_policy_weights_()


def shutdown_collector(collector: BaseCollector) -> None:
    """``collector.shutdown()``, keeping this process's torch thread count (TorchRL's multi-process
    collectors add the workers' threads back to it at shutdown)."""
    threads = torch.get_num_threads()
    collector.shutdown()
    torch.set_num_threads(threads)


def push_value_source_weights(collector: BaseCollector, value_source: ValueSource | None) -> None:
    """After a fit: copy the ensemble's weights into workers that cannot share memory (ray). A no-op
    for ``single`` (same object) and the multiprocessing backends (shared memory)."""
    remotes = getattr(collector, "remote_collectors", None)
    if value_source is None or not remotes:
        return
    import ray

    state = {k: v.detach().clone() for k, v in value_source.state_dict().items()}
    ray.get([r.cascade_execute.remote(f"{WORKER_ENSEMBLE_PATH}.load_state_dict", state) for r in remotes])


def build_replay_buffer(cfg, balanced: bool = False) -> TensorDictReplayBuffer | TakeoverBalancedReplayBuffer:
    """The learner's buffer: uniform, or with ``balanced`` and ``replay_buffer.takeover_share`` set, takeover rows
    kept apart with that share of every batch
    (:class:`~pe_rlhf.algorithms.proxy_q.takeover_replay.TakeoverBalancedReplayBuffer`)."""
    rb = cfg.replay_buffer
    share = rb.get("takeover_share")
    if balanced and share is not None:
        return TakeoverBalancedReplayBuffer(int(rb.size), int(rb.batch_size), float(share))
    return TensorDictReplayBuffer(storage=LazyTensorStorage(int(rb.size)), batch_size=int(rb.batch_size))


def build_collection_policy(cfg, actor):
    """What the collector runs: ``actor``, or with ``collector.exploration_noise`` > 0 (a deterministic actor,
    ``loss.objective=proxy_value``) ``actor`` then TorchRL's ``AdditiveGaussianModule`` (a constant sigma; no noise
    under deterministic exploration, so evaluation sees the bare actor)."""
    sigma = float(cfg.collector.get("exploration_noise", 0.0))
    if sigma <= 0 or not uses_proxy_values(cfg):
        return actor
    from tensordict.nn import TensorDictSequential
    from torchrl.modules import AdditiveGaussianModule

    noise = AdditiveGaussianModule(actor.spec, sigma_init=sigma, sigma_end=sigma, annealing_num_steps=1,
                                   action_key="action")
    return TensorDictSequential(actor, noise)


def build_optimizers(cfg, loss: PERLHFLoss) -> dict[str, torch.optim.Optimizer]:
    """One Adam per loss term, each over the parameters that term trains."""
    lr = float(cfg.optim.lr)
    if uses_proxy_values(cfg):
        return {"actor": make_adam(loss.actor_network_params.flatten_keys().values(), lr=lr),
                "qvalue": make_adam(loss.qvalue_network_params.flatten_keys().values(), lr=lr)}
    optimizers = {
        "actor": make_adam(loss.actor_network_params.flatten_keys().values(), lr=lr),
        "qvalue": make_adam(loss.qvalue_network_params.flatten_keys().values(), lr=lr),
        "intervention_qvalue": make_adam(
            loss.intervention_qvalue_network_params.flatten_keys().values(), lr=lr),
        "alpha": make_adam([loss.log_alpha], lr=lr),
    }
    if loss.has_disturbance_critic:
        optimizers["disturbance_qvalue"] = make_adam(
            loss.disturbance_qvalue_network_params.flatten_keys().values(), lr=lr)
    return optimizers


def find_transform(env, cls):
    """The env's transform of type ``cls`` (e.g. ``InterventionTransform``, ``RealtimePacing``), or None."""
    transform = getattr(env, "transform", None)
    candidates = list(transform) if hasattr(transform, "__iter__") else [transform]
    return next((t for t in candidates if isinstance(t, cls)), None)


def learner_device(cfg) -> torch.device | None:
    """``optim.device`` resolved: None for the CPU (the learner's actor acts, nothing is copied), else the
    device the loss module and its updates go to (``auto``: CUDA when torch sees one)."""
    setting = str(cfg.optim.device)
    if setting == "auto":
        setting = "cuda" if torch.cuda.is_available() else "cpu"
    if setting == "cpu":
        return None
    if setting.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"optim.device={cfg.optim.device!r}: torch sees no CUDA device here; use auto or cpu")
    return torch.device(setting)


def build_updater(cfg, loss: PERLHFLoss, optimizers: dict, soft_update: SoftUpdate, replay, actor,
                  update_threads: int, device: torch.device | None = None):
    """The learner (:mod:`pe_rlhf.algorithms.proxy_q.background_updates`): ``optim.updates_per_batch`` updates per
    ``collector.frames_per_batch`` frames, in a thread beside acting with ``optim.async_updates`` (on the
    ``update_threads - 1`` threads acting leaves), else inline: on ``optim.threads`` threads, ``auto``
    the cores other processes leave free (at most ``update_threads``; :class:`~pe_rlhf.threads.FreeCores`).
    ``device`` (:func:`learner_device`): where ``loss`` already is; the updater then acts on a CPU copy."""
    from fractions import Fraction

    from pe_rlhf.algorithms.proxy_q.background_updates import BackgroundUpdater, SyncUpdater

    kwargs = {"updates_per_step": Fraction(int(cfg.optim.updates_per_batch), int(cfg.collector.frames_per_batch)),
              "max_grad_norm": cfg.optim.max_grad_norm, "precision": str(cfg.optim.precision), "actor": actor,
              "device": device}
    if cfg.optim.async_updates:
        return BackgroundUpdater(loss, optimizers, soft_update, replay, threads=max(1, update_threads - 1), **kwargs)
    return SyncUpdater(loss, optimizers, soft_update, replay, threads=thread_budget(cfg.optim.threads, update_threads),
                       **kwargs)
