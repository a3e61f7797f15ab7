"""The physics policy ``pi_phy``: IDM longitudinal + MOBIL lane changes + lane-keeping steering.

It reads the simulator's state through :mod:`pe_rlhf.envs.perception` and returns
the normalised ``[steering, throttle]`` action every other policy speaks. By default it is a
*safe fallback*, as the authors' physics (MetaDrive's ``IDMPolicy``, whose leaders include static
objects) is:

- ``stop_for_obstacles=True`` (default): IDM treats an obstacle in its lane as a standing leader and
  brakes for it, but MOBIL still weighs vehicles only, so it never changes lane to pass one:
  the car stops behind a broken-down vehicle and waits (the failure the paper describes for its
  IDM-MOBIL, "often becomes stuck ... failing to take measures such as lane changes");
- ``stop_for_obstacles=False``: blind to static obstacles (vehicles only): it drives into them
  (this project's default before; the evaluation policy ``idm-mobil-blind``);
- ``see_obstacles=True``: both see obstacles (IDM brakes, MOBIL changes lane around them).

Three ways to use it:

- ``IDMMobilPolicy(...)(env)`` — a plain function of the simulator state;
- :class:`PhysicsPolicyModule` — a TorchRL/tensordict module writing ``"action"``;
- as the physics proposal inside the intervention transforms (later issue).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from highway_env import utils

from pe_rlhf.envs.action import controls_to_action
from pe_rlhf.envs.geometry import LANE_WIDTH
from pe_rlhf.physics.idm import IDMParams, idm_acceleration
from pe_rlhf.physics.mobil import LaneChangeAccelerations, MOBILParams, mobil_choose_lane
from pe_rlhf.envs.perception import Neighbour, ego_lane_slot, leader_and_follower, neighbours

# Lateral controller gains (highway-env's ControlledVehicle cascade).
TAU_HEADING = 0.2  # [s]
TAU_LATERAL = 0.6  # [s]
TAU_PURSUIT = 0.1  # [s]
MIN_CONTROL_SPEED = 2.0  # [m/s] floor on the speed used by the steering controller
ANTICIPATION_BRAKING = 2.0  # [m/s^2] used to slow down before a slower segment (curve, junction)


@dataclass(frozen=True)
class PhysicsConfig:
    """IDM/MOBIL parameters (paper defaults) and ablation switches."""

    idm: IDMParams = field(default_factory=IDMParams)
    mobil: MOBILParams = field(default_factory=MOBILParams)
    see_obstacles: bool = False  # IDM and MOBIL both see obstacles (brake and pass)
    stop_for_obstacles: bool = True  # IDM brakes for obstacles, MOBIL ignores them (stuck behind); False: blind
    use_idm: bool = True  # False: cruise at the desired speed, ignoring leaders ("MOBIL only")
    use_mobil: bool = True  # False: never change lane ("IDM only")


def _gap(ego_s: float, ego_len: float, lead: Neighbour) -> float:
    return lead.s - ego_s - (lead.length + ego_len) / 2


class IDMMobilPolicy:
    """Callable ``policy(env) -> np.ndarray [steering, throttle]`` on a ``DrivingEnv``."""

    def __init__(self, config: PhysicsConfig | None = None):
        self.config = config or PhysicsConfig()
        self.target_lane: int | None = None
        self._last_decision = -math.inf
        self._road = None
        self._resume = False  # a loaded plan waits for the restored episode's road (load_state_dict)

    def reset(self) -> None:
        self.target_lane = None
        self._last_decision = -math.inf
        self._road = None
        self._resume = False

    def state_dict(self, env=None) -> dict:
        """The lane plan, as JSON data: ``target_lane``, ``last_decision`` (the last MOBIL decision's env time, None
        for never) and ``planning`` (the plan belongs to the episode ``env`` is in; without ``env``, to any)."""
        road = getattr(getattr(env, "unwrapped", env), "road", None) if env is not None else self._road
        planning = self._resume or (self._road is not None and self._road is road)
        return {"target_lane": self.target_lane, "planning": planning,
                "last_decision": None if math.isinf(self._last_decision) else self._last_decision}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`; with ``planning``, the next call adopts the env's road as the plan's (a
        restored episode continues) instead of planning afresh."""
        self.target_lane = state["target_lane"]
        self._last_decision = -math.inf if state["last_decision"] is None else float(state["last_decision"])
        self._road, self._resume = None, bool(state["planning"])

    def __call__(self, env) -> np.ndarray:
        env = getattr(env, "unwrapped", env)
        slot, offset = ego_lane_slot(env)
        if env.road is not self._road and self._resume:  # restored mid-episode: keep the loaded plan
            self._road = env.road
        elif env.road is not self._road:  # every env.reset builds a new road: a new episode
            self._road, self.target_lane, self._last_decision = env.road, slot, -math.inf
        self._resume = False
        items = neighbours(env, include_obstacles=self.config.see_obstacles or self.config.stop_for_obstacles)
        if self.config.stop_for_obstacles and not self.config.see_obstacles:
            lateral_items = [n for n in items if not n.is_obstacle]  # MOBIL's view: vehicles only
        else:
            lateral_items = items
        v0 = self.desired_speed(env)
        if abs(self.target_lane - slot) > 1 or (self.target_lane != slot and not self._target_safe(env, lateral_items)):
            self.target_lane = slot  # moved by someone else, or the gap closed: re-plan from here
        if self.config.use_mobil and self.target_lane == slot and abs(offset) < 0.6:
            if env.time - self._last_decision >= self.config.mobil.lane_change_delay:
                self._last_decision = env.time
                self.target_lane = self._mobil(env, lateral_items, slot, v0)
        accel = self._idm(env, items, slot, v0)
        if self.target_lane != slot:
            accel = min(accel, self._idm(env, items, self.target_lane, v0))
        steering = self._steering(env, self.target_lane)
        return controls_to_action(steering, accel)

    # -- longitudinal ----------------------------------------------------------------
    def desired_speed(self, env) -> float:
        """Lane speed limit, lowered ahead of a slower segment so the car arrives at its limit."""
        route, k = env.route, env.route_segment
        lane = route.reference_lane(route.segments[k])
        v0 = float(lane.speed_limit)
        to_end = route.segment_start(route.segments[k]) + lane.length - env.progress
        for j in range(k + 1, min(k + 4, len(route.segments))):
            nxt = route.reference_lane(route.segments[j])
            v0 = min(v0, math.sqrt(nxt.speed_limit**2 + 2 * ANTICIPATION_BRAKING * max(to_end, 0.0)))
            to_end += nxt.length
        return max(v0, 1.0)

    def _idm(self, env, items, lane: int, v0: float) -> float:
        ego = env.vehicle
        if not self.config.use_idm:
            return idm_acceleration(ego.speed, v0, params=self.config.idm)
        lead, _ = leader_and_follower(items, lane, env.progress, env.route.lanes)
        if lead is None:
            return idm_acceleration(ego.speed, v0, params=self.config.idm)
        return idm_acceleration(ego.speed, v0, _gap(env.progress, ego.LENGTH, lead), max(lead.speed, 0.0),
                                params=self.config.idm)

    def _target_safe(self, env, items) -> bool:
        """MOBIL's safety criterion, re-checked every step while a lane change is under way."""
        ego, s = env.vehicle, env.progress
        lead, follow = leader_and_follower(items, self.target_lane, s, env.route.lanes)
        if lead is not None and _gap(s, ego.LENGTH, lead) < 0.0:
            return False
        if follow is None or follow.is_obstacle:
            return True
        gap = s - follow.s - (follow.length + ego.LENGTH) / 2
        target = float(getattr(follow.obj, "target_speed", 0.0)) or self.desired_speed(env)
        a = idm_acceleration(max(follow.speed, 0.0), target, gap, ego.speed, params=self.config.idm)
        return a >= -self.config.mobil.max_safe_braking

    # -- lateral -----------------------------------------------------------------------
    def _mobil(self, env, items, slot: int, v0: float) -> int:
        ego, p = env.vehicle, self.config.idm
        s, lanes = env.progress, env.route.lanes
        old_lead, old_follow = leader_and_follower(items, slot, s, lanes)

        def follower_acc(f: Neighbour | None, lead_s: float | None, lead_len: float, lead_v: float):
            if f is None or f.is_obstacle:
                return None
            target = float(getattr(f.obj, "target_speed", v0)) or v0
            if lead_s is None:
                return idm_acceleration(max(f.speed, 0.0), target, params=p)
            gap = lead_s - f.s - (lead_len + f.length) / 2
            return idm_acceleration(max(f.speed, 0.0), target, gap, lead_v, params=p)

        def ego_acc(lead: Neighbour | None) -> float:
            if lead is None:
                return idm_acceleration(ego.speed, v0, params=p)
            return idm_acceleration(ego.speed, v0, _gap(s, ego.LENGTH, lead), max(lead.speed, 0.0), params=p)

        candidates = {}
        for lane in (slot - 1, slot + 1):
            if not 0 <= lane < lanes:
                continue
            new_lead, new_follow = leader_and_follower(items, lane, s, lanes)
            lead_args = (new_lead.s, new_lead.length, new_lead.speed) if new_lead else (None, 0.0, 0.0)
            old_lead_args = (old_lead.s, old_lead.length, old_lead.speed) if old_lead else (None, 0.0, 0.0)
            nf_before = follower_acc(new_follow, *lead_args)
            of_before = follower_acc(old_follow, s, ego.LENGTH, ego.speed)
            candidates[lane] = LaneChangeAccelerations(
                ego_current=ego_acc(old_lead),
                ego_target=ego_acc(new_lead),
                new_follower_before=nf_before,
                new_follower_after=None if nf_before is None else follower_acc(new_follow, s, ego.LENGTH, ego.speed),
                old_follower_before=of_before,
                old_follower_after=None if of_before is None else follower_acc(old_follow, *old_lead_args),
            )
        return mobil_choose_lane(slot, candidates, self.config.mobil)

    def _steering(self, env, slot: int) -> float:
        """Front-wheel angle [rad] to track lane slot ``slot`` along the route (pursuit + heading loop)."""
        ego, route, k = env.vehicle, env.route, env.route_segment
        lane = env.road.network.get_lane((*route.segments[k], slot))
        s, lat = lane.local_coordinates(ego.position)
        ahead = s + ego.speed * TAU_PURSUIT
        if ahead > lane.length and k + 1 < len(route.segments):
            nxt = env.road.network.get_lane((*route.segments[k + 1], slot))
            future_heading = nxt.heading_at(ahead - lane.length)
        else:
            future_heading = lane.heading_at(min(ahead, lane.length))
        speed = max(ego.speed, MIN_CONTROL_SPEED)  # 1/speed gains would saturate at a standstill
        heading_cmd = math.asin(float(np.clip(-lat / TAU_LATERAL / speed, -1, 1)))
        heading_ref = future_heading + float(np.clip(heading_cmd, -math.pi / 4, math.pi / 4))
        rate = utils.wrap_to_pi(heading_ref - ego.heading) / TAU_HEADING
        slip = math.asin(float(np.clip(ego.LENGTH / 2 / speed * rate, -1, 1)))
        return math.atan(2 * math.tan(slip))


__all__ = ["IDMMobilPolicy", "PhysicsConfig", "LANE_WIDTH"]
