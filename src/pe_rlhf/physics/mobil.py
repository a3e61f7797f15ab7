"""MOBIL lane-change model (Kesting, Treiber & Helbing, 2007).

Units: accelerations in m/s^2, times in s. Inputs are IDM accelerations
computed by the caller; pure maths, no simulator dependency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class MOBILParams:
    """MOBIL parameters (PE-RLHF paper values as defaults).

    Units: politeness dimensionless in [0, 1]; threshold (a_th) and
    max_safe_braking (b_safe, positive magnitude) in m/s^2; lane_change_delay
    (minimum time between lane-change decisions) in s.
    """

    politeness: float = 0.1
    threshold: float = 0.2
    max_safe_braking: float = 2.0
    lane_change_delay: float = 1.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.politeness <= 1.0):
            raise ValueError(f"MOBILParams.politeness must be in [0, 1], got {self.politeness!r}")
        for name in ("threshold", "max_safe_braking", "lane_change_delay"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"MOBILParams.{name} must be finite and >= 0, got {value!r}")


@dataclass
class LaneChangeAccelerations:
    """IDM accelerations describing one candidate lane change.

    Units: m/s^2. ``ego_current``/``ego_target``: ego's acceleration in its current
    lane / in the target lane behind its new leader. ``new_follower_*``: the
    target-lane follower before/after the ego cuts in (None if none).
    ``old_follower_*``: the current-lane follower before/after the ego leaves
    (None if none). Each before/after pair must be both set or both None.
    """

    ego_current: float
    ego_target: float
    new_follower_before: float | None = None
    new_follower_after: float | None = None
    old_follower_before: float | None = None
    old_follower_after: float | None = None

    def __post_init__(self) -> None:
        for who in ("new_follower", "old_follower"):
            before, after = getattr(self, f"{who}_before"), getattr(self, f"{who}_after")
            if (before is None) != (after is None):
                raise ValueError(f"{who}_before and {who}_after must both be set or both None")


def _params(params: MOBILParams | None) -> MOBILParams:
    return MOBILParams() if params is None else params


def mobil_safe(acc: LaneChangeAccelerations, params: MOBILParams | None = None) -> bool:
    """Safety criterion: new follower's acceleration after the change >= -b_safe.

    Units: m/s^2. True when there is no new follower.
    """
    if acc.new_follower_after is None:
        return True
    return acc.new_follower_after >= -_params(params).max_safe_braking


def mobil_incentive(acc: LaneChangeAccelerations, params: MOBILParams | None = None) -> float:
    """Incentive: ego gain + p * (new-follower change + old-follower change).

    Units: m/s^2. Missing followers contribute 0.
    """
    p = _params(params)
    others = 0.0
    if acc.new_follower_before is not None and acc.new_follower_after is not None:
        others += acc.new_follower_after - acc.new_follower_before
    if acc.old_follower_before is not None and acc.old_follower_after is not None:
        others += acc.old_follower_after - acc.old_follower_before
    return acc.ego_target - acc.ego_current + p.politeness * others


def mobil_should_change(
    acc: LaneChangeAccelerations, params: MOBILParams | None = None, bias: float = 0.0
) -> bool:
    """Whether to change lane: safe and incentive >= threshold - bias.

    Units: bias in m/s^2. Positive bias makes the change more attractive (e.g.
    towards the lane the route needs, or a keep-right rule); negative deters it.
    """
    p = _params(params)
    return mobil_safe(acc, p) and mobil_incentive(acc, p) >= p.threshold - bias


def mobil_choose_lane(
    current_lane: int,
    candidates: dict[int, LaneChangeAccelerations],
    params: MOBILParams | None = None,
    biases: dict[int, float] | None = None,
) -> int:
    """Pick the lane with the highest incentive + bias among qualifying changes.

    Units: biases in m/s^2, keyed by lane index (missing = 0). Returns
    ``current_lane`` when no candidate is safe and passes the threshold.
    """
    p = _params(params)
    biases = biases or {}
    best_lane, best_score = current_lane, -math.inf
    for lane, acc in candidates.items():
        if lane == current_lane:
            continue
        bias = biases.get(lane, 0.0)
        if not mobil_should_change(acc, p, bias):
            continue
        score = mobil_incentive(acc, p) + bias
        if score > best_score:
            best_lane, best_score = lane, score
    return best_lane
