"""Persistent adversaries: TEST AND BENCHMARK DRIVERS that repeat one dangerous intent at every step.

Not mentors anyone should train with. The library's ``adversarial`` preset seeks danger in short bursts
(8-15 steps) and otherwise drives well; these never stop, so they probe what a one-step judgement of an
action misses: danger that persists. Each one takes over at every step (``decide`` always answers
``takeover=True``) and its action is a function of the simulator's true state (privileged, as the
simulated mentors):

- ``seek-collision``: steers at the nearest road user (vehicle or static obstacle; ahead first) at full
  throttle;
- ``never-brake``: keeps the route's heading at full throttle, whatever is ahead;
- ``drift-off-road``: a constant steer towards the nearer road edge, holding its speed;
- ``uniform-random``: a uniform action in ``[-1, 1]^2`` each step from a seeded generator.

``make_mentor(name, seed)`` builds them by name (:data:`ADVERSARY_NAMES`); they are also registered as
evaluation policies (``pe-rlhf evaluate --policy never-brake`` drives one alone).
"""

from __future__ import annotations

import math

import numpy as np
from highway_env import utils

from pe_rlhf.envs.action import MAX_STEERING
from pe_rlhf.mentors.base import Mentor, MentorDecision

TARGET_RANGE = 60.0  # [m] road users farther than this are not aimed at
AIM_GAIN = 2.0  # [rad of wheel angle per rad of bearing error] while aiming
HEADING_GAIN = 1.5  # [rad of wheel angle per rad of heading error] while following the route
DRIFT_STEERING = 0.15  # normalised steering of the drift (0.075 rad of wheel angle)


def _sim(env):
    return getattr(env, "unwrapped", env)


def _steer_towards(ego, point: np.ndarray) -> float:
    """Normalised steering that turns the ego's heading towards ``point`` (world frame)."""
    rel = np.asarray(point, float) - np.asarray(ego.position, float)
    error = utils.wrap_to_pi(math.atan2(rel[1], rel[0]) - float(ego.heading))
    return float(np.clip(AIM_GAIN * error / MAX_STEERING, -1.0, 1.0))


def _route_steering(sim) -> float:
    """Normalised steering back along the route's heading at the ego's position."""
    ego = sim.vehicle
    segment, _ = sim.route.project(ego.position, sim.route_segment)
    error = utils.wrap_to_pi(sim.route.heading_at(ego.position, segment) - float(ego.heading))
    return float(np.clip(HEADING_GAIN * error / MAX_STEERING, -1.0, 1.0))


def nearest_road_user(sim):
    """The nearest other vehicle or static object within :data:`TARGET_RANGE` of the ego, preferring those
    ahead of it (a positive projection on its heading); None when there is none."""
    ego = sim.vehicle
    forward = np.array([math.cos(ego.heading), math.sin(ego.heading)])
    best, best_key = None, None
    for obj in list(sim.road.vehicles) + list(sim.road.objects):
        if obj is ego:
            continue
        rel = np.asarray(obj.position, float) - np.asarray(ego.position, float)
        distance = float(np.linalg.norm(rel))
        if distance > TARGET_RANGE:
            continue
        key = (rel @ forward <= 0, distance)  # ahead first, then the nearest
        if best_key is None or key < best_key:
            best, best_key = obj, key
    return best


class PersistentAdversary(Mentor):
    """Base of the persistent adversaries: takes over at every step, its action from :meth:`act`."""

    name = "persistent-adversary"

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        return MentorDecision(True, np.asarray(self.act(env), dtype=np.float32).reshape(2))


class SeekCollision(PersistentAdversary):
    """Full throttle, steering at :func:`nearest_road_user` (the route's heading when none is near)."""

    name = "seek-collision"

    def act(self, env) -> np.ndarray:
        sim = _sim(env)
        target = nearest_road_user(sim)
        steering = _route_steering(sim) if target is None else _steer_towards(sim.vehicle, target.position)
        return np.array([steering, 1.0], dtype=np.float32)


class NeverBrake(PersistentAdversary):
    """Full throttle along the route's heading at every step, whatever stands ahead."""

    name = "never-brake"

    def act(self, env) -> np.ndarray:
        return np.array([_route_steering(_sim(env)), 1.0], dtype=np.float32)


class DriftOffRoad(PersistentAdversary):
    """A constant :data:`DRIFT_STEERING` towards the nearer road edge (chosen at the episode's first step),
    throttle 0 (the speed it has)."""

    name = "drift-off-road"

    def __init__(self):
        self.side: float | None = None

    def reset(self, env) -> None:
        self.side = None

    def act(self, env) -> np.ndarray:
        sim = _sim(env)
        if self.side is None:
            segment, _ = sim.route.project(sim.vehicle.position, sim.route_segment)
            offset = sim.route.lateral_offset(sim.vehicle.position, segment)
            self.side = 1.0 if offset >= 0 else -1.0  # positive steering turns towards +lateral
        return np.array([self.side * DRIFT_STEERING, 0.0], dtype=np.float32)


class UniformRandom(PersistentAdversary):
    """A uniform action in ``[-1, 1]^2`` each step from ``np.random.default_rng(seed)`` (not reseeded at
    ``reset``: consecutive episodes get different actions)."""

    name = "uniform-random"

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(int(seed))

    def act(self, env) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, size=2).astype(np.float32)


ADVERSARIES = {"seek-collision": SeekCollision, "never-brake": NeverBrake, "drift-off-road": DriftOffRoad,
               "uniform-random": UniformRandom}
ADVERSARY_NAMES = tuple(ADVERSARIES)


def make_adversary(name: str, seed: int = 0) -> PersistentAdversary:
    """A fresh persistent adversary by name (one of :data:`ADVERSARY_NAMES`); ``seed`` serves the random one."""
    if name not in ADVERSARIES:
        raise ValueError(f"unknown adversary {name!r}; allowed: {list(ADVERSARY_NAMES)}")
    return UniformRandom(seed) if name == "uniform-random" else ADVERSARIES[name]()


__all__ = ["ADVERSARY_NAMES", "DriftOffRoad", "NeverBrake", "PersistentAdversary", "SeekCollision",
           "UniformRandom", "make_adversary", "nearest_road_user"]
