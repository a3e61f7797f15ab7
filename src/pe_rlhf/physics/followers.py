"""Road users behind the ego in the physics forecast: they drive on along their route under the IDM.

The forecast (:mod:`pe_rlhf.physics.safety`) moves the ego car along a candidate trajectory; a road user
*behind* it is another driver, who brakes for the ego only once the ego is in its lane, and no harder than its
car can (``ACC_MAX``). So hard braking in front of a fast follower, or turning across a lane at walking pace,
fails when the follower cannot stop in time: the simulator's background cars are highway-env IDM vehicles and
this module predicts them with their own parameters (``COMFORT_ACC_MAX``, ``COMFORT_ACC_MIN``,
``DISTANCE_WANTED``, ``TIME_WANTED``, ``DELTA``, ``target_speed``, ``ACC_MAX``) and highway-env's rules.

Where it drives: along the path its own lane-keeping controller steers it on, through the next lanes of its route
(:func:`pe_rlhf.physics.road_users.cached_path`, the path the road users ahead are forecast on), at the speed its
IDM gives; past the path's end it drives straight on. When it brakes: as highway-env decides it. The ego is its
leader where ``Road.neighbour_vehicles`` finds it ahead: on the lane of its route the follower is on, or on a lane
connected to that lane's end or start (the env searches connected lanes), by ``on_lane`` with the 1 m margin
(within 1 m of the lane's sides, from 5 m before its start to 5 m past its end). The IDM's gap is then
``lane_distance_to``: the distance in the coordinates of the follower's *own* lane, which past a curved lane's end
is no distance at all (a circular lane's coordinates wrap: a car on a roundabout's ring hardly brakes for the ego
on the next ring segment until it is on that segment itself; train scene 4, a rear-end at 5 m/s). highway-env also
tests the lane its car is *closest* to, which near a merge can be another lane: the forecast's follower brakes no
sooner than the simulator's there. Other leaders of the follower (a car between it and the ego) are not modelled: it
would drive through them, which can only make the forecast more cautious.
"""

from __future__ import annotations

import bisect
import math
import weakref
from dataclasses import dataclass

import numpy as np

from pe_rlhf.physics.road_users import cached_path, follows_lanes

ON_LANE_MARGIN = 1.0  # [m] highway-env's neighbour_vehicles: a vehicle this far outside a lane is still in it
LEADER_MIN_GAP = 0.01  # [m] highway-env's utils.not_zero floor of the IDM's gap
PATH_STEP = 0.1  # [s] the step of a follower's path (the forecast's)
PATH_SECONDS = 4.0  # [s] of a follower's path at its speed (then straight on, within the forecast's 6 s)


@dataclass(frozen=True, eq=False)
class Follower:
    """One road user behind the ego: its path, its route's lanes, size and IDM parameters; its moving state lives
    apart (``(s, speed)`` in :meth:`Followers.initial`, ``s`` the distance along its path) so a forecast can
    branch."""

    path: tuple  # (distances, xs, ys, headings): float lists of its path's points (distance along the path first)
    lanes: tuple  # the lanes of its route the path runs along, in order
    searched: tuple  # per lane of ``lanes``: ((lane, offset), ...) where highway-env looks for its leader
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

    def pose(self, s: float) -> tuple[np.ndarray, float]:
        """``(position (2,), heading)`` at distance ``s`` along the path (straight on past its end; Python lists:
        one pose is a few floats, where numpy's calls cost more)."""
        d, x, y, h = self.path
        if s >= d[-1]:
            return np.array((x[-1] + (s - d[-1]) * math.cos(h[-1]), y[-1] + (s - d[-1]) * math.sin(h[-1]))), h[-1]
        i = max(bisect.bisect_right(d, s), 1)
        w = (s - d[i - 1]) / (d[i] - d[i - 1]) if d[i] > d[i - 1] else 0.0
        return np.array((x[i - 1] + w * (x[i] - x[i - 1]), y[i - 1] + w * (y[i] - y[i - 1]))), \
            h[i - 1] + w * (h[i] - h[i - 1])

    def lane_at(self, position: np.ndarray) -> int:
        """Which lane of its route (an index into ``lanes``) the follower is on at ``position``: the first whose end
        it has not passed, else the last."""
        for k, lane in enumerate(self.lanes[:-1]):
            if lane.local_coordinates(position)[0] <= lane.length:
                return k
        return len(self.lanes) - 1


def is_lane_follower(vehicle) -> bool:
    """Whether ``vehicle`` drives along a lane under highway-env's IDM (a follower this module can forecast)."""
    return getattr(vehicle, "lane", None) is not None and hasattr(vehicle, "COMFORT_ACC_MAX")


def route_lanes(vehicle, count: int = 4) -> list:
    """The indices of the lane ``vehicle`` steers to (its target lane) and of the next ``count - 1`` of its route
    (highway-env's ``next_lane``; its route is copied: ``next_lane`` consumes it)."""
    network = vehicle.road.network
    index = getattr(vehicle, "target_lane_index", None) or vehicle.lane_index
    route = list(getattr(vehicle, "route", None) or [])
    indices = [index]
    for _ in range(count - 1):
        lane = network.get_lane(index)
        following = network.next_lane(index, route=route, position=lane.position(lane.length, 0.0))
        if following == index:
            break
        index = following
        indices.append(index)
    return indices


def searched_lanes(network, index) -> tuple:
    """``((lane, offset), ...)``: where ``Road.neighbour_vehicles`` with connected lanes looks for a vehicle on lane
    ``index``'s behalf, in its order: the lane, the lanes leaving its end node (offset: its length), the lanes
    arriving at its start node (offset: minus their length); of each road, the lane of the same id (else the
    first)."""
    lane = network.get_lane(index)
    _from, _to, _id = index
    out = [(lane, 0.0)]
    for lanes in network.graph.get(_to, {}).values():
        if lanes:
            out.append((lanes[_id] if _id < len(lanes) else lanes[0], float(lane.length)))
    for roads in network.graph.values():
        lanes = roads.get(_from)
        if lanes:
            previous = lanes[_id] if _id < len(lanes) else lanes[0]
            out.append((previous, -float(previous.length)))
    return tuple(out)


_MODELS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # vehicle -> (its state, its Follower)
_BOXES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # lane -> the box around its on_lane region


def _on_lane_box(lane) -> tuple[float, float, float, float]:
    """``(x min, y min, x max, y max)`` around the region where ``on_lane`` with the 1 m margin holds (sampled every
    2 m along the lane, widened by a metre for the chord of a curved lane between samples)."""
    box = _BOXES.get(lane)
    if box is None:
        half = max(lane.width_at(0.0), lane.width_at(lane.length)) / 2 + ON_LANE_MARGIN + 1.0
        s = np.linspace(-lane.VEHICLE_LENGTH, lane.length + lane.VEHICLE_LENGTH, max(int(lane.length / 2.0), 2) + 6)
        points = np.array([lane.position(si, lat) for si in s for lat in (-half, half)])
        box = _BOXES[lane] = (*points.min(0).tolist(), *points.max(0).tolist())
    return box


def follower_model(vehicle) -> Follower | None:
    """The IDM model of ``vehicle``, or None for a road user without a lane (it is forecast elsewhere); built once
    per state of the vehicle (the forecasts of one decision share it)."""
    if not is_lane_follower(vehicle):
        return None
    key = (float(vehicle.position[0]), float(vehicle.position[1]), float(vehicle.heading), float(vehicle.speed),
           vehicle.lane_index, getattr(vehicle, "target_lane_index", None),
           tuple(getattr(vehicle, "route", None) or ()),
           float(getattr(vehicle, "target_speed", vehicle.speed)))
    hit = _MODELS.get(vehicle)
    if hit is None or hit[0] != key:
        hit = _MODELS[vehicle] = (key, _build_model(vehicle))
    return hit[1]


def _build_model(vehicle) -> Follower:
    speed = float(vehicle.speed)
    if follows_lanes(vehicle):
        points, headings = cached_path(vehicle, PATH_STEP, int(round(PATH_SECONDS / PATH_STEP)))
    else:
        points, headings = np.asarray(vehicle.position, float)[None], np.array([float(vehicle.heading)])
    steps = np.hypot(*np.diff(points, axis=0).T) if len(points) > 1 else np.zeros(0)
    path = (np.concatenate([[0.0], np.cumsum(steps)]).tolist(), points[:, 0].tolist(), points[:, 1].tolist(),
            np.asarray(headings, float).tolist())
    target_speed = float(getattr(vehicle, "target_speed", speed))
    lane = vehicle.lane
    if getattr(lane, "speed_limit", None) is not None:
        target_speed = float(np.clip(target_speed, 0.0, lane.speed_limit))
    network = vehicle.road.network
    indices = route_lanes(vehicle)
    return Follower(path, tuple(network.get_lane(i) for i in indices),
                    tuple(searched_lanes(network, i) for i in indices), float(vehicle.LENGTH), float(vehicle.WIDTH),
                    float(vehicle.COMFORT_ACC_MAX), float(vehicle.COMFORT_ACC_MIN), float(vehicle.DISTANCE_WANTED),
                    float(vehicle.TIME_WANTED), float(vehicle.DELTA), max(target_speed, 0.1),
                    float(getattr(vehicle, "ACC_MAX", 6.0)), float(getattr(vehicle, "MAX_SPEED", 40.0)))


class Followers:
    """The moving road users behind the ego within ``near`` metres, forecast under the IDM (module docstring).

    State for one forecast branch: ``(s, speed)``, two float arrays ``(F,)`` (the distance along each one's path
    and its speed); :meth:`step` returns a new state (branches never share one)."""

    def __init__(self, env, near: float):
        ego = env.vehicle
        forward = np.array([math.cos(ego.heading), math.sin(ego.heading)])
        self.models: list[Follower] = []
        v0 = []
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
                v0.append(speed)
        self._initial = (np.zeros(len(v0)), np.array(v0, float))

    def __bool__(self) -> bool:
        return bool(self.models)

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        return self._initial

    def step(self, state, ego_position: np.ndarray, ego_heading: float, ego_speed: float, dt: float):
        """One ``dt``: each follower's IDM acceleration from the current positions (the ego as its leader while
        on its lane, ahead), then its motion along its path; highway-env's order (all act, then all move)."""
        s, v = state
        ego_velocity = ego_speed * np.array([math.cos(ego_heading), math.sin(ego_heading)])
        accel = np.empty_like(v)
        for j, m in enumerate(self.models):
            a = m.comfort_acc * (1.0 - (max(v[j], 0.0) / m.target_speed) ** m.delta)
            position, heading = m.pose(float(s[j]))
            gap = self._gap_to_ego(m, position, ego_position)
            if gap is not None:
                dv = v[j] - float(ego_velocity @ np.array([math.cos(heading), math.sin(heading)]))
                wanted = m.distance_wanted + v[j] * m.time_wanted + v[j] * dv / (2 * math.sqrt(
                    -m.comfort_acc * m.comfort_dec))
                gap = gap if abs(gap) > LEADER_MIN_GAP else math.copysign(LEADER_MIN_GAP, gap)
                a -= m.comfort_acc * (wanted / gap) ** 2
            accel[j] = min(max(a, -m.acc_max), m.acc_max)
        limit = np.array([m.max_speed for m in self.models])
        new_v = np.clip(v + accel * dt, 0.0, limit)
        return s + v * dt, new_v  # highway-env moves on the speed before the update

    def poses(self, state):
        """``(position (2,), heading, length, width, velocity (2,))`` of each follower in ``state``."""
        s, v = state
        out = []
        for j, m in enumerate(self.models):
            position, heading = m.pose(float(s[j]))
            out.append((position, heading, m.length, m.width, v[j] * np.array([math.cos(heading), math.sin(heading)])))
        return out

    @staticmethod
    def _gap_to_ego(model: Follower, position: np.ndarray, ego_position: np.ndarray) -> float | None:
        """The IDM's gap to the ego while the ego is the follower's leader, as highway-env computes both
        (module docstring: ``neighbour_vehicles`` over the searched lanes, then ``lane_distance_to`` in the
        follower's own lane's coordinates, which can be negative), the follower at ``position`` (on its path); None
        when it is not its leader."""
        k = model.lane_at(position)
        lane = model.lanes[k]
        s_self = lane.local_coordinates(position)[0]
        x, y = float(ego_position[0]), float(ego_position[1])
        for searched, offset in model.searched[k]:
            box = _on_lane_box(searched)
            if not (box[0] <= x <= box[2] and box[1] <= y <= box[3]):
                continue  # nowhere near the lane: not on it (a few comparisons instead of its coordinates)
            s_ego, lat_ego = searched.local_coordinates(ego_position)
            if not searched.on_lane(ego_position, s_ego, lat_ego, margin=ON_LANE_MARGIN):
                continue
            if s_ego + offset < s_self:
                return None  # found behind it: not its leader
            return float(lane.local_coordinates(ego_position)[0] - s_self)
        return None


__all__ = ["Follower", "Followers", "follower_model", "is_lane_follower", "route_lanes", "searched_lanes"]
