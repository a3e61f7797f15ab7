"""Run a policy on fixed scenes and summarise the spec's metrics (mean ± population std).

Metrics per episode (spec §6): episodic return, success, safety violation (summed
per-step cost), travel distance [m], travel velocity [km/h, mean over steps],
overtake count, plus the failure flags and route completion.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

import numpy as np
from tqdm.auto import tqdm

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.evaluation.policies import Policy

MEAN_STD_METRICS = (
    "episodic_return",
    "safety_violation",
    "travel_distance",
    "travel_velocity",
    "overtake_count",
    "route_completion",
)
RATE_METRICS = {  # JSON key -> EpisodeResult flag
    "success_rate": "success",
    "crash_vehicle_rate": "crash_vehicle",
    "crash_object_rate": "crash_object",
    "out_of_road_rate": "out_of_road",
    "timeout_rate": "timeout",
}
FAILURE_CAUSES = ("crash_vehicle", "crash_object", "out_of_road", "timeout")  # priority order


@dataclass
class EpisodeResult:
    """The metrics of one evaluation episode on scene ``scene_seed``."""

    scene_seed: int
    episodic_return: float
    success: bool
    safety_violation: float  # sum of per-step cost
    travel_distance: float  # [m] final odometer
    travel_velocity: float  # [km/h] mean of per-step velocity
    overtake_count: int
    crash_vehicle: bool
    crash_object: bool
    out_of_road: bool
    timeout: bool  # truncated at the horizon without success
    route_completion: float
    steps: int
    override_steps: int | None = None  # steps a runtime shield executed its fallback (None: no shield)
    decision_latency: float | None = None  # [s] mean time of a shield's decision (None: no shield)

    @property
    def failure_cause(self) -> str | None:
        """None on success, else the first set flag of :data:`FAILURE_CAUSES` (one cause per episode)."""
        if self.success:
            return None
        return next((c for c in FAILURE_CAUSES if getattr(self, c)), "timeout")


def run_episode(env, policy: Policy, scene_seed: int) -> EpisodeResult:
    """Drive ``policy`` (already reset) on scene ``scene_seed`` of ``env`` until the episode ends.

    ``env`` may be a gymnasium wrapper of the driving env (a runtime shield): the policy reads its ``unwrapped``
    simulator, and a step's ``info`` with ``shield_override`` / ``shield_latency`` is counted in
    ``override_steps`` / ``decision_latency``."""
    obs, info = env.reset(options={"scene_seed": int(scene_seed)})
    sim = getattr(env, "unwrapped", env)
    episodic_return = cost = velocity_sum = 0.0
    steps = 0
    overrides, latencies = None, []
    terminated = truncated = False
    while not (terminated or truncated):
        action = policy(obs, sim)
        obs, reward, terminated, truncated, info = env.step(action)
        episodic_return += reward
        cost += info["cost"]
        velocity_sum += info["velocity"]
        steps += 1
        if "shield_override" in info:
            overrides = (overrides or 0) + bool(info["shield_override"])
            latencies.append(float(info.get("shield_latency", float("nan"))))
    return EpisodeResult(
        scene_seed=int(scene_seed),
        episodic_return=float(episodic_return),
        success=bool(info["success"]),
        safety_violation=float(cost),
        travel_distance=float(info["travel_distance"]),
        travel_velocity=float(velocity_sum / max(steps, 1)),
        overtake_count=int(info["overtakes"]),
        crash_vehicle=bool(info["crash_vehicle"]),
        crash_object=bool(info["crash_object"]),
        out_of_road=bool(info["out_of_road"]),
        timeout=bool(truncated and not info["success"]),
        route_completion=float(info["route_completion"]),
        steps=steps,
        override_steps=overrides,
        decision_latency=float(np.mean(latencies)) if latencies else None,
    )


def _mean_std(values: Sequence[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"mean": float("nan"), "std": float("nan")}
    return {"mean": float(a.mean()), "std": float(a.std())}


@dataclass
class EvaluationSummary:
    """The episodes of one evaluation, with the config and policy name that produced them."""

    episodes: list[EpisodeResult]
    config: DrivingConfig = field(default_factory=DrivingConfig)
    policy: str | None = None

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes])) if self.episodes else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """The JSON structure: ``{metric: {"mean", "std"}}`` for every metric, plus
        ``failure_breakdown`` (one cause per failed episode), ``episodes``, ``seeds``,
        ``policy``, ``env_config`` and ``episodes_detail`` (per-episode dicts)."""
        eps = self.episodes
        out: dict[str, Any] = {}
        for key in MEAN_STD_METRICS:
            out[key] = _mean_std([getattr(e, key) for e in eps])
        for key, flag in RATE_METRICS.items():
            out[key] = _mean_std([float(getattr(e, flag)) for e in eps])
        causes = [e.failure_cause for e in eps if e.failure_cause is not None]
        out["failure_breakdown"] = {c: causes.count(c) for c in FAILURE_CAUSES}
        shielded = [e for e in eps if e.override_steps is not None]
        if shielded:  # a runtime shield drove: the share of steps it overrode, the time of a decision
            out["override_share"] = sum(e.override_steps for e in shielded) / max(sum(e.steps for e in shielded), 1)
            out["decision_latency_ms"] = _mean_std([1000 * e.decision_latency for e in shielded])
        out["episodes"] = len(eps)
        out["seeds"] = [e.scene_seed for e in eps]
        out["policy"] = self.policy
        out["env_config"] = self.config.to_dict()
        out["episodes_detail"] = [asdict(e) for e in eps]
        return out


def evaluate(
    policy: Policy,
    seeds: Sequence[int],
    config: DrivingConfig | dict | None = None,
    progress: bool = True,
    name: str | None = None,
    wrap_env=None,
) -> EvaluationSummary:
    """Run one episode of ``policy`` per scene seed, in order, on one env.

    In: a policy (reset before each episode), scene seeds, a DrivingConfig (or dict,
    or None for defaults), whether to show a tqdm bar, an optional policy name for
    the report, and ``wrap_env`` (a callable ``env -> env``, e.g. ``pe_rlhf.wrappers.SafetyShieldWrapper``: the
    summary then reports ``override_share`` and ``decision_latency_ms``). Out: an :class:`EvaluationSummary`.
    """
    config = config if isinstance(config, DrivingConfig) else DrivingConfig.from_dict(config)
    env = make_gym_env(config)
    if wrap_env is not None:
        env = wrap_env(env)
    results: list[EpisodeResult] = []
    try:
        bar = tqdm(list(seeds), desc=f"evaluate {name or ''}".strip(), unit="ep", disable=not progress)
        for seed in bar:
            policy.reset()
            results.append(run_episode(env, policy, seed))
            bar.set_postfix(success=f"{np.mean([r.success for r in results]):.2f}")
        bar.close()
    finally:
        env.close()
    return EvaluationSummary(results, config, name)
