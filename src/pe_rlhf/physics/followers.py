"""Road users behind the ego in the physics forecast: they drive on along their lane under the IDM.

The forecast (:mod:`pe_rlhf.physics.safety`) moves the ego car along a candidate trajectory; a road user
*behind* it is another driver, who brakes for the ego only once the ego is in its lane, and no harder than its
car can (``ACC_MAX``). So hard braking in front of a fast follower, or turning across a lane at walking pace,
fails when the follower cannot stop in time: the simulator's background cars are highway-env IDM vehicles and
this module predicts them with their own parameters (``COMFORT_ACC_MAX``, ``COMFORT_ACC_MIN``,
``DISTANCE_WANTED``, ``TIME_WANTED``, ``DELTA``, ``target_speed``, ``ACC_MAX``) and highway-env's rules: the
ego is the follower's leader while its centre is within 1 m of the follower's lane (current or target lane)
and ahead of it (``Road.neighbour_vehicles``); otherwise the follower drives the free-road IDM term. A
follower keeps its lateral offset in its lane; past the lane's end the lane's geometry is extrapolated. Other
leaders of the follower (a car between it and the ego) are not modelled: it would drive through them, which
can only make the forecast more cautious.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ON_LANE_MARGIN = 1.0  # [m] highway-env's neighbour_vehicles: a vehicle this far outside a lane is still in it
LEADER_MIN_GAP = 0.01  # [m] highway-env's utils.not_zero floor of the IDM's gap


@dataclass(frozen=True)
class Follower:
    """One road user behind the ego: its lanes, size and IDM parameters; its moving state lives apart
    (``(s, speed)`` in :meth:`Followers.initial`) so a forecast can branch."""

    lanes: tuple  # its lane, and its target lane when it is changing lanes
    lateral: float
    length: float
    width: float
    comfort_acc: float
    comfort_dec: float
    distance_wanted: float
    time_wanted: float
    delta: float
    target_speed: float
    acc_max: float
    max_speed: float


def follower_model(vehicle) -> Follower | None:
    """The IDM model of ``vehicle``, or None for a road user without a lane (it is forecast elsewhere)."""
    lane = getattr(vehicle, "lane", None)
    if lane is None or not hasattr(vehicle, "COMFORT_ACC_MAX"):
        return None
    lanes = [lane]
    network = vehicle.road.network
    target = getattr(vehicle, "target_lane_index", None)
    if target is not None and target != vehicle.lane_index:
        lanes.append(network.get_lane(target))
    s, lateral = lane.local_coordinates(vehicle.position)
    target_speed = float(getattr(vehicle, "target_speed", vehicle.speed))
    if getattr(lane, "speed_limit", None) is not None:
        target_speed = float(np.clip(target_speed, 0.0, lane.speed_limit))
    return Follower(tuple(lanes), float(lateral), float(vehicle.LENGTH), float(vehicle.WIDTH),
                    float(vehicle.COMFORT_ACC_MAX), float(vehicle.COMFORT_ACC_MIN), float(vehicle.DISTANCE_WANTED),
                    float(vehicle.TIME_WANTED), float(vehicle.DELTA), max(target_speed, 0.1),
                    float(getattr(vehicle, "ACC_MAX", 6.0)), float(getattr(vehicle, "MAX_SPEED", 40.0)))


class Followers:
    """The moving road users behind the ego within ``near`` metres, forecast under the IDM (module docstring).

    State for one forecast branch: ``(s, speed)``, two float arrays ``(F,)`` (the progress along each one's own
    lane and its speed); :meth:`step` returns a new state (branches never share one)."""

    def __init__(self, env, near: float):
        ego = env.vehicle
        forward = np.array([math.cos(ego.heading), math.sin(ego.heading)])
        self.models: list[Follower] = []
        s0, v0 = [], []
        for vehicle in env.road.vehicles:
            if vehicle is ego:
                continue
            rel = np.asarray(vehicle.position, float) - np.asarray(ego.position, float)
            speed = float(getattr(vehicle, "speed", 0.0))
            if speed <= 0.1 or rel @ forward >= 0 or np.linalg.norm(rel) > near:
                continue  # standing, ahead, or out of reach: forecast as the others (safety._others)
            model = follower_model(vehicle)
            if model is not None:
                self.models.append(model)
                s0.append(model.lanes[0].local_coordinates(vehicle.position)[0])
                v0.append(speed)
        self._initial = (np.array(s0, float), np.array(v0, float))

    def __bool__(self) -> bool:
        return bool(self.models)

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        return self._initial

    def step(self, state, ego_position: np.ndarray, ego_heading: float, ego_speed: float, dt: float):
        """One ``dt``: each follower's IDM acceleration from the current positions (the ego as its leader while
        in its lane, ahead), then its motion along its lane; highway-env's order (all act, then all move)."""
        s, v = state
        ego_velocity = ego_speed * np.array([math.cos(ego_heading), math.sin(ego_heading)])
        accel = np.empty_like(v)
        for j, m in enumerate(self.models):
            a = m.comfort_acc * (1.0 - (max(v[j], 0.0) / m.target_speed) ** m.delta)
            gap = self._gap_to_ego(m, s[j], ego_position)
            if gap is not None:
                direction = self._direction(m, s[j])
                dv = v[j] - float(ego_velocity @ direction)
                wanted = m.distance_wanted + v[j] * m.time_wanted + v[j] * dv / (2 * math.sqrt(
                    -m.comfort_acc * m.comfort_dec))
                a -= m.comfort_acc * (wanted / max(gap, LEADER_MIN_GAP)) ** 2
            accel[j] = min(max(a, -m.acc_max), m.acc_max)
        limit = np.array([m.max_speed for m in self.models])
        new_v = np.clip(v + accel * dt, 0.0, limit)
        return s + v * dt, new_v  # highway-env moves on the speed before the update

    def poses(self, state):
        """``(position (2,), heading, length, width, velocity (2,))`` of each follower in ``state``."""
        s, v = state
        out = []
        for j, m in enumerate(self.models):
            lane = m.lanes[0]
            heading = float(lane.heading_at(s[j]))
            out.append((np.asarray(lane.position(s[j], m.lateral), float), heading, m.length, m.width,
                        v[j] * np.array([math.cos(heading), math.sin(heading)])))
        return out

    @staticmethod
    def _direction(model: Follower, s: float) -> np.ndarray:
        heading = model.lanes[0].heading_at(s)
        return np.array([math.cos(heading), math.sin(heading)])

    @staticmethod
    def _gap_to_ego(model: Follower, s: float, ego_position: np.ndarray) -> float | None:
        """Centre distance along the follower's lane to the ego while the ego is its leader (in one of its
        lanes, ahead of it); the least over its lanes; None when it is not its leader."""
        own = model.lanes[0]
        position = own.position(s, model.lateral)
        best = None
        for lane in model.lanes:
            s_ego, lat_ego = lane.local_coordinates(ego_position)
            if abs(lat_ego) > lane.width_at(s_ego) / 2 + ON_LANE_MARGIN:
                continue
            s_self = lane.local_coordinates(position)[0] if lane is not own else s
            if s_ego >= s_self and (best is None or s_ego - s_self < best):
                best = float(s_ego - s_self)
        return best


__all__ = ["Follower", "Followers", "follower_model"]
