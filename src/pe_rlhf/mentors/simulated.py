"""Simulated mentors: the privileged driver degraded by a skill profile, with a takeover rule.

``SimulatedMentor`` = :class:`~pe_rlhf.mentors.driver.PrivilegedDriver` (its *intended*
action: the clean plan of a driver who sees the true scene) + a :class:`SkillProfile`
(how it fails to execute that plan) + a :class:`~pe_rlhf.mentors.takeover.TakeoverRule`
(when it grabs the wheel) + a seeded ``np.random.Generator``. Per env step the
*executed* action is built as:

1. reaction delay: the intended action of ``reaction_delay`` steps ago (a deque);
2. a manoeuvre, if one is under way: an error (``steer`` pulse to a random side, an
   unneeded hard ``brake``, or ``throttle`` when it should brake; 3-6 steps, started
   with probability ``error_rate`` per step) or, for adversarial profiles, a danger
   seek (steering at the nearest road user ahead or the road edge; 8-15 steps, started
   with probability ``danger_seeking``);
3. Gaussian noise of std ``action_noise`` on both dimensions, then clipping to [-1, 1].

Fatigue: ``error_rate`` and ``action_noise`` are multiplied by
``min(1 + fatigue_rate * controlled_steps / 1000, max_fatigue)`` where
``controlled_steps`` counts the steps on which the mentor held control (it persists
across episodes). Everything is deterministic for a given seed.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pe_rlhf.envs.action import MAX_STEERING
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.driver import DriverParams, PrivilegedDriver
from pe_rlhf.mentors.takeover import TakeoverRule
from pe_rlhf.envs.perception import ego_lane_slot

ERROR_KINDS = ("steer", "brake", "throttle")
ERROR_STEPS = (3, 10)  # inclusive range of an error's duration [steps]
SEEK_STEPS = (8, 15)  # inclusive range of a danger seek's duration [steps]
SEEK_RANGE = 40.0  # [m] a danger seek aims at road users this close ahead


@dataclass(frozen=True)
class SkillProfile:
    """How well a simulated mentor executes its plan; every field is validated.

    ``action_noise``: std of Gaussian noise on each normalised action entry;
    ``reaction_delay``: steps between planning an action and executing it;
    ``error_rate``: per-step probability of starting a wrong manoeuvre;
    ``fatigue_rate``: growth of the noise/error multiplier per 1000 controlled steps,
    capped at ``max_fatigue``; ``danger_seeking``: per-step probability of steering at a
    road user or the road edge (adversarial); ``speed_factor``: desired speed scale;
    ``free_level``/``min_span``: the takeover rule's parameters; ``steer_tolerance`` /
    ``throttle_tolerance``: the std of its belief over acceptable actions (``TakeoverRule.sigma``: how
    much driving style it accepts); ``stall_speed`` [m/s]: the takeover rule's stall test fires once the car has
    been slower than this for 2 s while the mentor's own plan accelerates (``TakeoverRule.stall_speed``);
    ``seek_takes_over``: a danger seek grabs the wheel (an adversarial
    mentor takes over *in order to* do harm, so its takeovers executed as they come lower a driver's success).
    """

    action_noise: float = 0.0
    reaction_delay: int = 0
    error_rate: float = 0.0
    fatigue_rate: float = 0.0
    max_fatigue: float = 3.0
    danger_seeking: float = 0.0
    speed_factor: float = 1.0
    free_level: float = 0.95
    min_span: int = 10
    steer_tolerance: float = 0.6
    throttle_tolerance: float = 0.6
    # 5 m/s (2 m/s before issue 41): a person takes over a car that makes no progress; competent drivers' takeovers
    # are unchanged, a 4 m/s crawler is taken over at 0.86 of its steps (docs/experiments/learner.md)
    stall_speed: float = 5.0
    seek_takes_over: bool = False

    def __post_init__(self) -> None:
        def bad(name: str, allowed: str) -> None:
            raise ValueError(f"SkillProfile.{name}={getattr(self, name)!r} is invalid: {allowed}")

        for name in ("reaction_delay", "min_span"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool):
                bad(name, "must be an integer")
        if not isinstance(self.seek_takes_over, bool):
            bad("seek_takes_over", "must be true or false")
        for name in ("action_noise", "error_rate", "fatigue_rate", "max_fatigue", "danger_seeking",
                     "speed_factor", "free_level", "steer_tolerance", "throttle_tolerance"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
                    or not math.isfinite(value):
                bad(name, "must be a finite number")
        if not 0.0 <= self.action_noise <= 1.0:
            bad("action_noise", "must be in [0, 1]")
        if not 0 <= self.reaction_delay <= 20:
            bad("reaction_delay", "must be in [0, 20] steps")
        for name in ("error_rate", "danger_seeking"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                bad(name, "must be a probability in [0, 1]")
        if self.fatigue_rate < 0.0:
            bad("fatigue_rate", "must be >= 0")
        if self.max_fatigue < 1.0:
            bad("max_fatigue", "must be >= 1")
        if not 0.1 <= self.speed_factor <= 1.5:
            bad("speed_factor", "must be in [0.1, 1.5]")
        if not 0.0 < self.free_level < 1.0:
            bad("free_level", "must be in (0, 1)")
        if self.min_span < 1:
            bad("min_span", "must be >= 1 step")
        if not (math.isfinite(self.stall_speed) and self.stall_speed >= 0.0):
            bad("stall_speed", "must be a finite speed >= 0 m/s")
        for name in ("steer_tolerance", "throttle_tolerance"):
            if not 0.0 < getattr(self, name) <= 2.0:
                bad(name, "must be in (0, 2] (normalised action units)")


# The amateur tires over a whole run: fatigue x2 after 10K controlled steps (about the end of a 10K-step
# warm-up, where the rule fires on most of the agent's proposals), x3 (the cap) after 20K, so its mistakes
# keep growing through the online phase (issue 7's value-takeover analysis). With 1.0 it hit the cap
# within the first 2K warm-up steps and stayed there.
PRESETS: dict[str, SkillProfile] = {
    "professional": SkillProfile(action_noise=0.01),
    # Errors start with probability error_rate a step and last 3-10 steps, so the share of steps inside one is
    # ~ 6.5 r / (1 + 6.5 r). At 0.06 (before 2026-12-03) that was 27% of the amateur's steps fresh and 51% at full
    # fatigue (12-19% hard braking; train scenes 0-9): labels a learner cannot use (HACO crawled, 0.30 with 25
    # timeouts). At 0.01: 5.5% fresh, 15% at full fatigue (hard braking 2.8% / 7.9%), alone 0.80 / 1.00 success.
    "amateur": SkillProfile(action_noise=0.08, reaction_delay=3, error_rate=0.01, fatigue_rate=0.1,
                            speed_factor=0.95),
    # Adversarial where it is decided, in its executed actions: its danger seeks grab the wheel. With IDM-MOBIL
    # driving and its takeovers executed as they come (train scenes 0-9): 0.01 and seeks that only ran while
    # it held control raised IDM-MOBIL's success (0.50 -> 0.80, its privileged takeovers pass obstacles);
    # seeks that take over: 0.01 -> 0.60 success / 0.40 violations, 0.03 -> 0.10 / 0.90, 0.06 -> 0.00 / 1.00.
    "adversarial": SkillProfile(action_noise=0.1, reaction_delay=3, error_rate=0.08, fatigue_rate=1.0,
                                danger_seeking=0.03, speed_factor=1.1, seek_takes_over=True),
}
ALIASES = {"bad": "adversarial"}


def preset(name: str) -> SkillProfile:
    """The preset profile ``name`` (aliases allowed); unknown names raise listing the allowed ones."""
    key = ALIASES.get(name, name)
    if key not in PRESETS:
        raise ValueError(f"unknown skill preset {name!r}; allowed: {sorted(PRESETS) + sorted(ALIASES)}")
    return PRESETS[key]


def driver_params_for(profile: SkillProfile) -> DriverParams:
    """The driver of a profile: its speed, and lane-keeping loops slowed by 0.1 s / 0.2 s per
    step of reaction delay (a delayed driver with the undelayed gains weaves)."""
    d = profile.reaction_delay
    return DriverParams(speed_factor=profile.speed_factor, tau_heading=0.2 + 0.1 * d, tau_lateral=0.6 + 0.2 * d)


class SimulatedMentor(Mentor):
    """A privileged driver with a skill profile and a takeover rule (see the module docstring).

    Call ``decide(env, agent_action)`` once per env step (it advances the takeover rule), or
    ``act(env)`` when the mentor drives alone; ``act`` before ``decide`` on the same env step
    computes that step's action once (both return it). After a call, ``last_intended`` holds
    the clean plan and ``last_action`` the executed action. A new ``env.road`` (every
    ``env.reset``) starts a new episode even without ``reset``.
    """

    def __init__(self, profile: SkillProfile | None = None, seed: int = 0, name: str = "simulated",
                 rule: TakeoverRule | None = None, driver_params: DriverParams | None = None):
        self.profile = profile or SkillProfile()
        self.name, self.seed = name, int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.driver = PrivilegedDriver(driver_params or driver_params_for(self.profile))
        self.rule = rule or TakeoverRule(sigma=(self.profile.steer_tolerance, self.profile.throttle_tolerance),
                                         free_level=self.profile.free_level, min_span=self.profile.min_span,
                                         stall_speed=self.profile.stall_speed)
        self.controlled_steps = 0
        self._resume = False
        self._new_episode(None)

    def _new_episode(self, road) -> None:
        self._road = road
        self._queue: deque[np.ndarray] = deque(maxlen=self.profile.reaction_delay + 1)
        self._manoeuvre: dict[str, Any] | None = None
        self._memo_steps: int | None = None
        self.last_intended = np.zeros(2, dtype=np.float32)
        self.last_action = np.zeros(2, dtype=np.float32)
        self.driver.reset()
        self.rule.reset()

    # -- mentor interface ----------------------------------------------------------------
    def reseed(self, seed: int) -> None:
        """As built with ``seed``: a fresh RNG, no fatigue, no episode under way."""
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.controlled_steps = 0
        self._resume = False
        self._new_episode(None)

    def reset(self, env) -> None:
        """Episode start: clears the delay queue, manoeuvre and takeover span (fatigue persists)."""
        self._resume = False
        self._new_episode(getattr(getattr(env, "unwrapped", env), "road", None))

    @property
    def manoeuvre(self) -> str | None:
        """The kind of wrong manoeuvre under way (``"steer"``, ``"brake"``, ``"throttle"``, ``"seek"``), else None."""
        return None if self._manoeuvre is None else str(self._manoeuvre["kind"])

    @property
    def fatigue(self) -> float:
        """The current noise/error multiplier (>= 1)."""
        p = self.profile
        return min(1.0 + p.fatigue_rate * self.controlled_steps / 1000.0, p.max_fatigue)

    def act(self, env) -> np.ndarray:
        """The executed action for the current state (delayed, erroneous, noisy), float32 ``(2,)``."""
        return self._step(env).copy()

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        """Takeover by the rule against the *intended* action; the decision carries the executed one."""
        action = self._step(env)
        takeover = self.rule.step(getattr(env, "unwrapped", env), agent_action, self.last_intended)
        if self.profile.seek_takes_over and self._manoeuvre is not None and self._manoeuvre["kind"] == "seek":
            takeover = True
        if takeover:
            self.controlled_steps += 1
        return MentorDecision(bool(takeover), action.copy())

    def state_dict(self) -> dict[str, Any]:
        return {
            "profile": asdict(self.profile),
            "seed": self.seed,
            "controlled_steps": self.controlled_steps,
            "rule": self.rule.state_dict(),
            "rng": self.rng.bit_generator.state,
            "queue": [a.tolist() for a in self._queue],
            "manoeuvre": None if self._manoeuvre is None else dict(self._manoeuvre),
            "target_lane": self.driver.target_lane,
            "last_slot": self.driver._last_slot,
            "last_intended": self.last_intended.tolist(),
            "last_action": self.last_action.tolist(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore; the next call continues the episode on whatever road the env holds then."""
        profile = SkillProfile(**state["profile"])
        if profile != self.profile:
            raise ValueError(f"state was saved by a mentor with profile {profile}, this one has {self.profile}")
        self.controlled_steps = int(state["controlled_steps"])
        self.rng.bit_generator.state = state["rng"]
        self._new_episode(None)
        self.rule.load_state_dict(state["rule"])
        self._queue.extend(np.asarray(a, dtype=np.float32) for a in state["queue"])
        self._manoeuvre = None if state["manoeuvre"] is None else dict(state["manoeuvre"])
        self.driver.target_lane = state["target_lane"]
        self.driver._last_slot = state.get("last_slot")
        self.last_intended = np.asarray(state.get("last_intended", (0.0, 0.0)), dtype=np.float32)
        self.last_action = np.asarray(state.get("last_action", (0.0, 0.0)), dtype=np.float32)
        self._resume = True

    # -- one step ------------------------------------------------------------------------
    def _step(self, env) -> np.ndarray:
        env = getattr(env, "unwrapped", env)
        if env.road is not self._road:
            if self._resume:  # restored mid-episode: adopt this road, keep the loaded state
                self._road, self.driver._road = env.road, env.road
            else:
                self._new_episode(env.road)
        self._resume = False
        if self._memo_steps == env.steps:
            return self.last_action
        intended = np.asarray(self.driver(env), dtype=np.float32)
        self._queue.append(intended)
        action = self._queue[0].astype(np.float64)
        fatigue = self.fatigue
        self._maybe_start_manoeuvre(env, fatigue)
        if self._manoeuvre is not None:
            action = self._apply_manoeuvre(env, action)
        if self.profile.action_noise > 0:
            action = action + self.rng.normal(0.0, self.profile.action_noise * fatigue, size=2)
        self.last_intended = intended
        self.last_action = np.clip(action, -1.0, 1.0).astype(np.float32)
        self._memo_steps = env.steps
        return self.last_action

    def _maybe_start_manoeuvre(self, env, fatigue: float) -> None:
        p, rng = self.profile, self.rng
        if self._manoeuvre is not None:
            return
        if p.danger_seeking > 0 and rng.random() < p.danger_seeking:
            self._manoeuvre = {"kind": "seek", "steps": int(rng.integers(SEEK_STEPS[0], SEEK_STEPS[1] + 1)),
                               "side": self._edge_side(env)}
        elif p.error_rate > 0 and rng.random() < min(p.error_rate * fatigue, 1.0):
            kind = ERROR_KINDS[int(rng.integers(len(ERROR_KINDS)))]
            value = {"steer": float(rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.5)),
                     "brake": float(-rng.uniform(0.6, 1.0)), "throttle": float(rng.uniform(0.4, 0.8))}[kind]
            self._manoeuvre = {"kind": kind, "steps": int(rng.integers(ERROR_STEPS[0], ERROR_STEPS[1] + 1)),
                               "value": value}

    def _edge_side(self, env) -> float:
        """+1 or -1: towards the nearer road edge (a random side in a middle lane)."""
        slot, _ = ego_lane_slot(env)
        if slot == 0:
            return -1.0
        if slot == env.route.lanes - 1:
            return 1.0
        return float(self.rng.choice([-1.0, 1.0]))

    def _apply_manoeuvre(self, env, action: np.ndarray) -> np.ndarray:
        m = self._manoeuvre
        kind = m["kind"]
        if kind == "steer":
            action[0] += m["value"]
        elif kind == "brake":
            action[1] = m["value"]
        elif kind == "throttle":
            action[1] = max(action[1], m["value"])
        else:
            action = self._seek_action(env, m["side"])
        m["steps"] -= 1
        if m["steps"] <= 0:
            self._manoeuvre = None
        return action

    @staticmethod
    def _seek_action(env, side: float) -> np.ndarray:
        """Steer at the nearest road user ahead within ``SEEK_RANGE``, else at the road edge; accelerate."""
        ego = env.vehicle
        best, best_d = None, SEEK_RANGE
        for o in list(env.road.vehicles) + list(env.road.objects):
            rel = o.position - ego.position
            d = float(np.linalg.norm(rel))
            ahead = rel[0] * math.cos(ego.heading) + rel[1] * math.sin(ego.heading)
            if o is not ego and ahead > 2.0 and d < best_d:
                best, best_d = o, d
        if best is None:
            return np.array([0.6 * side, 0.5])
        rel = best.position - ego.position
        angle = math.atan2(rel[1], rel[0]) - ego.heading
        angle = (angle + math.pi) % (2 * math.pi) - math.pi
        return np.array([float(np.clip(2.0 * angle / MAX_STEERING, -1, 1)), 0.8])
