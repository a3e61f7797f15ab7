"""A privileged rule-based driver: sees the true scene (lanes, vehicles, obstacles, route).

It is the skill core of the simulated mentors. Compared with the physics policy it

- treats obstacles as standing leaders (IDM stops for them);
- plans its lane from what lies ahead: each lane slot is scored by the free distance
  to the first blocking object within ``LOOK_AHEAD`` and the speed of the traffic
  there; it moves one lane at a time towards the best slot when the gap is safe
  (MOBIL's safety criterion on the new follower plus a minimum front/rear clearance);
- waits behind a blocked lane until a gap opens instead of changing unsafely;
- brakes for any vehicle whose constant-velocity path closes on it with
  time-to-collision under ``TTC_BRAKE`` (cut-ins, merging traffic).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from highway_env import utils

from pe_rlhf.envs.action import controls_to_action
from pe_rlhf.physics.idm import IDMParams, idm_acceleration
from pe_rlhf.envs.perception import Neighbour, ego_lane_slot, leader_and_follower, neighbours, occupies
from pe_rlhf.physics.policy import MIN_CONTROL_SPEED, IDMMobilPolicy, PhysicsConfig

LOOK_AHEAD = 90.0  # [m] lane planning horizon
TTC_BRAKE = 2.0  # [s]
MIN_FRONT_GAP = 6.0  # [m] bumper gap to accept in the target lane ahead
MIN_REAR_GAP = 5.0  # [m] bumper gap to accept in the target lane behind
LANE_SWITCH_BONUS = 25.0  # [m] free distance a new lane must gain to be worth a change


@dataclass(frozen=True)
class DriverParams:
    """The privileged driver's car-following and planning parameters."""

    idm: IDMParams = IDMParams(max_acceleration=2.5, comfortable_braking=4.0, minimum_gap=4.0, time_headway=1.2)
    speed_factor: float = 1.0  # desired speed = factor * lane speed limit
    max_safe_braking: float = 3.0  # [m/s^2] MOBIL safety: braking imposed on the new follower
    # Lane-keeping cascade (highway-env's): lateral offset -> heading -> yaw rate. A driver
    # with a reaction delay needs slower loops, or the delayed loop rings (weaving).
    tau_heading: float = 0.2  # [s]
    tau_lateral: float = 0.6  # [s]
    tau_pursuit: float = 0.1  # [s] look-ahead for the reference heading
    max_heading_offset: float = math.pi / 4  # [rad] largest angle to the lane taken to reach it
    # True: a lane change someone else made (the agent, while the mentor watched) becomes the plan, as a
    # person accepts a safe manoeuvre it would not have chosen. Off by default: measured, the professional's
    # executed takeover share on IDM-MOBIL-oracle rose (0.42 -> 0.48, train scenes 0-4; docs/results/claims).
    adopt_lane: bool = False


class PrivilegedDriver:
    """Callable ``driver(env) -> action``; plans with the simulator's true state."""

    def __init__(self, params: DriverParams | None = None):
        self.params = params or DriverParams()
        # Reuse the physics policy's speed anticipation and lane-keeping controller.
        self._tracker = IDMMobilPolicy(PhysicsConfig(idm=self.params.idm, see_obstacles=True))
        self.target_lane: int | None = None
        self._road = None
        self._last_slot: int | None = None

    def reset(self) -> None:
        self.target_lane, self._road, self._last_slot = None, None, None

    def __call__(self, env) -> np.ndarray:
        env = getattr(env, "unwrapped", env)
        slot, offset = ego_lane_slot(env)
        if env.road is not self._road or self.target_lane is None or abs(self.target_lane - slot) > 1:
            self._road, self.target_lane = env.road, slot  # new episode, or moved by someone else
        elif self.params.adopt_lane and slot != self._last_slot and self.target_lane == self._last_slot:
            self.target_lane = slot  # the car changed lane without this plan: adopt it
        self._last_slot = slot
        items = neighbours(env, include_obstacles=True)
        v0 = self._tracker.desired_speed(env) * self.params.speed_factor
        if self.target_lane == slot and abs(offset) < 1.0:
            self.target_lane = self._plan_lane(env, items, slot)
        elif self.target_lane != slot and not self._gap_ok(env, items, self.target_lane):
            self.target_lane = slot  # abort: the gap closed
        accel = self._lane_accel(env, items, slot, v0)
        if self.target_lane != slot:
            accel = min(accel, self._lane_accel(env, items, self.target_lane, v0))
        accel = min(accel, self._ttc_brake(env, items))
        steering = self._steering(env, self.target_lane)
        return controls_to_action(steering, accel)

    def _steering(self, env, slot: int) -> float:
        """Front-wheel angle [rad] tracking lane slot ``slot``: pursuit + heading loop (``DriverParams`` taus)."""
        p, ego, route, k = self.params, env.vehicle, env.route, env.route_segment
        lane = env.road.network.get_lane((*route.segments[k], slot))
        s, lat = lane.local_coordinates(ego.position)
        ahead = s + ego.speed * p.tau_pursuit
        if ahead > lane.length and k + 1 < len(route.segments):
            future_heading = env.road.network.get_lane((*route.segments[k + 1], slot)).heading_at(ahead - lane.length)
        else:
            future_heading = lane.heading_at(min(ahead, lane.length))
        speed = max(ego.speed, MIN_CONTROL_SPEED)  # 1/speed gains would saturate at a standstill
        heading_cmd = math.asin(float(np.clip(-lat / p.tau_lateral / speed, -1, 1)))
        heading_ref = future_heading + float(np.clip(heading_cmd, -p.max_heading_offset, p.max_heading_offset))
        rate = utils.wrap_to_pi(heading_ref - ego.heading) / p.tau_heading
        slip = math.asin(float(np.clip(ego.LENGTH / 2 / speed * rate, -1, 1)))
        return math.atan(2 * math.tan(slip))

    # -- planning --------------------------------------------------------------------
    def _free_distance(self, env, items: list[Neighbour], lane: int) -> tuple[float, float]:
        """(free distance to the first slow/standing object in ``lane``, speed of its leader)."""
        s = env.progress
        lead, _ = leader_and_follower(items, lane, s - 2.0, env.route.lanes)
        free, speed = LOOK_AHEAD, 99.0
        blocking = [n for n in items if n.s > s - 2.0 and self._in_lane(n, lane, env) and
                    (n.is_obstacle or n.speed < 1.0)]
        if blocking:
            free = min(free, min(n.s for n in blocking) - s)
        if lead is not None:
            speed = lead.speed
        return free, speed

    @staticmethod
    def _in_lane(n: Neighbour, lane: int, env) -> bool:
        return occupies(n, lane, env.route.lanes)

    def _plan_lane(self, env, items, slot: int) -> int:
        free_here, _ = self._free_distance(env, items, slot)
        if free_here >= LOOK_AHEAD:
            return slot
        best, best_free = slot, free_here
        for lane in (slot - 1, slot + 1):
            if not 0 <= lane < env.route.lanes:
                continue
            free, _ = self._free_distance(env, items, lane)
            if free > best_free + LANE_SWITCH_BONUS * (free_here > 40.0) and self._gap_ok(env, items, lane):
                best, best_free = lane, free
        return best

    def _gap_ok(self, env, items, lane: int) -> bool:
        """Front/rear clearance in ``lane`` and MOBIL's safety criterion for its follower."""
        ego, s = env.vehicle, env.progress
        lead, follow = leader_and_follower(items, lane, s, env.route.lanes)
        if lead is not None and lead.s - s - (lead.length + ego.LENGTH) / 2 < MIN_FRONT_GAP:
            return False
        if follow is not None and not follow.is_obstacle:
            gap = s - follow.s - (follow.length + ego.LENGTH) / 2
            if gap < MIN_REAR_GAP:
                return False
            target = float(getattr(follow.obj, "target_speed", follow.speed)) or 1.0
            a = idm_acceleration(max(follow.speed, 0.0), max(target, 1.0), gap, ego.speed)
            if a < -self.params.max_safe_braking:
                return False
        elif follow is not None and s - follow.s - (follow.length + ego.LENGTH) / 2 < 1.0:
            return False
        return True

    def _lane_accel(self, env, items, lane: int, v0: float) -> float:
        ego, s = env.vehicle, env.progress
        lead, _ = leader_and_follower(items, lane, s, env.route.lanes)
        if lead is None:
            return idm_acceleration(ego.speed, v0, params=self.params.idm)
        gap = lead.s - s - (lead.length + ego.LENGTH) / 2
        return idm_acceleration(ego.speed, v0, gap, max(lead.speed, 0.0), params=self.params.idm)

    def _ttc_brake(self, env, items) -> float:
        """Hard braking if any road user closes in on the ego's path within ``TTC_BRAKE``."""
        ego = env.vehicle
        heading = np.array([math.cos(ego.heading), math.sin(ego.heading)])
        for n in items:
            rel = n.obj.position - ego.position
            forward = float(rel @ heading)
            if forward <= 0:
                continue
            lateral = abs(float(rel @ np.array([-heading[1], heading[0]])))
            if lateral > (ego.WIDTH + n.width) / 2 + 0.3:
                continue
            closing = ego.speed - float(n.obj.velocity @ heading)
            gap = forward - (ego.LENGTH + n.length) / 2
            if closing > 0 and gap / closing < TTC_BRAKE:
                return -self.params.idm.max_braking
        return math.inf
