"""Road users ahead of the ego in the physics forecast: where each one is at every instant, computed once a forecast.

The forecast (:mod:`pe_rlhf.physics.safety`) tests the ego's body against every road user near it after each of
the simulator's sub-steps; this module says where they are then. A lane-following vehicle (highway-env's
``ControlledVehicle``, which the traffic's ``IDMVehicle`` s are) drives on along its planned route at constant
speed, steered as the simulator steers it: highway-env's lane-keeping controller
(``ControlledVehicle.steering_control``: pursuit of its target lane's centre ``TAU_PURSUIT`` seconds ahead, lateral
gain ``KP_LATERAL``, heading gain ``KP_HEADING``), the next lane of its route at a lane's end (``follow_road``,
``RoadNetwork.next_lane``), and the kinematic bicycle of ``Vehicle.step``. So a car on a curved or turning lane is
forecast along that lane, its heading lagging the lane's as in the simulator: on a hand-built bend, at its target
speed, within 0.04 m and 0.01 rad of the simulator over the 3 s (``tests/physics/test_road_users.py``); a car
circulating in a roundabout (train scene 8) was 0.5 m off after 0.6 s and 8.1 m after 3 s as a straight line at its
velocity, 0.09 m and 1.3 m in this model (the rest its IDM acceleration). Its path is integrated once a decision at
the forecast's step (0.1 s) and interpolated linearly for the sub-steps between (:func:`cached_path`). Not
forecast: a lane change the vehicle has not started yet (MOBIL), a change of speed (the IDM: braking behind a queue
or at a stop line, slowing into a bend, accelerating out of one), a crashed vehicle's stop. The forecast's default
(:class:`RoadUsers` ``model="lanes_or_velocity"``) therefore also moves each lane follower straight on at its
velocity, the model before, and counts a contact with either path: on never-brake's train scene 7 a truck's lane
change at a roundabout's entry was caught only by the straight path (docs/experiments/shield-calibration.md). Every
other road user keeps its velocity: a static obstacle stays where it is.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

TURN_LIMIT = math.pi / 4  # [rad] highway-env's clip of the lateral controller's heading command


def _not_zero(x: float, eps: float = 1e-2) -> float:
    """highway-env's ``utils.not_zero``: ``x``, or ``eps`` with ``x``'s sign where it is closer to 0."""
    return x if abs(x) > eps else (eps if x >= 0 else -eps)


def lane_following_path(vehicle, dt: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """``(positions (steps + 1, 2), headings (steps + 1,))`` of ``vehicle`` (a highway-env ``ControlledVehicle``) at
    ``0, dt, ..., steps * dt`` seconds: its own lane-keeping controller along its route at its current speed
    (module docstring). The vehicle is not changed (its route is copied: ``next_lane`` consumes it)."""
    network = vehicle.road.network
    target_index = vehicle.target_lane_index
    target = network.get_lane(target_index)
    route = list(vehicle.route) if vehicle.route else None
    x, y, heading, speed = float(vehicle.position[0]), float(vehicle.position[1]), float(vehicle.heading), \
        float(vehicle.speed)
    half, divisor = vehicle.LENGTH / 2, _not_zero(speed)
    kp_lateral, kp_heading, tau = vehicle.KP_LATERAL, vehicle.KP_HEADING, vehicle.TAU_PURSUIT
    max_steering = vehicle.MAX_STEERING_ANGLE
    positions, headings = np.empty((steps + 1, 2)), np.empty(steps + 1)
    positions[0], headings[0] = (x, y), heading
    for i in range(1, steps + 1):
        position = np.array((x, y))
        s, lateral = target.local_coordinates(position)
        if s > target.length - target.VEHICLE_LENGTH / 2:  # follow_road: the next lane of its route
            following = network.next_lane(target_index, route=route, position=position)
            if following != target_index:
                target_index, target = following, network.get_lane(following)
                s, lateral = target.local_coordinates(position)
        # ControlledVehicle.steering_control, in floats
        reference = target.heading_at(s + speed * tau) + min(max(math.asin(
            min(max(-kp_lateral * lateral / divisor, -1.0), 1.0)), -TURN_LIMIT), TURN_LIMIT)
        rate = kp_heading * ((reference - heading + math.pi) % (2 * math.pi) - math.pi)
        slip = math.asin(min(max(half / divisor * rate, -1.0), 1.0))
        steering = min(max(math.atan(2 * math.tan(slip)), -max_steering), max_steering)
        # Vehicle.step: the kinematic bicycle
        beta = math.atan(0.5 * math.tan(steering))
        x += speed * math.cos(heading + beta) * dt
        y += speed * math.sin(heading + beta) * dt
        heading += speed * math.sin(beta) / half * dt
        positions[i], headings[i] = (x, y), heading
    return positions, headings


_PATHS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # vehicle -> (its state, dt, steps), its path


def cached_path(vehicle, dt: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lane_following_path`, computed once per state of ``vehicle``: the forecasts of one decision (each
    candidate action, the recovery, the repeated action) share it. Read-only arrays."""
    key = (float(vehicle.position[0]), float(vehicle.position[1]), float(vehicle.heading), float(vehicle.speed),
           vehicle.target_lane_index, tuple(vehicle.route or ()), float(dt), int(steps))
    hit = _PATHS.get(vehicle)
    if hit is not None and hit[0] == key:
        return hit[1]
    path = lane_following_path(vehicle, dt, steps)
    for array in path:
        array.flags.writeable = False
    _PATHS[vehicle] = (key, path)
    return path


def follows_lanes(obj) -> bool:
    """Whether ``obj`` is forecast along its lanes: a moving, uncrashed highway-env lane-following vehicle."""
    return (hasattr(obj, "target_lane_index") and hasattr(obj, "KP_LATERAL") and hasattr(obj, "TAU_PURSUIT")
            and not getattr(obj, "crashed", False) and float(getattr(obj, "speed", 0.0)) > 0.0)


MODELS = ("velocity", "lanes", "lanes_or_velocity")  # SafetyForecastConfig.road_users


class RoadUsers:
    """The road users ahead of the ego in one forecast, with their poses at every sub-step (module docstring).

    ``objects``: the highway-env vehicles and objects; ``dt`` [s] the forecast's step, ``steps`` its length in steps,
    ``substeps`` the simulator's sub-steps a step; ``model``: a lane-following vehicle drives along its lanes
    ("lanes"), keeps its velocity ("velocity", the model before), or either ("lanes_or_velocity": it is forecast
    twice, and a contact with either path is a contact). :meth:`near` ``(k, ...)``: those near a point after sub-step
    ``k`` (0: now); ``positions`` ``(K + 1, M, 2)`` and ``headings`` ``(K + 1, M)``: every forecast path's pose at
    every sub-step (``M`` paths: one a road user, two for a lane follower under "lanes_or_velocity")."""

    def __init__(self, objects: list, dt: float, steps: int, substeps: int, model: str = "lanes"):
        if model not in MODELS:
            raise ValueError(f"RoadUsers model={model!r} is invalid: allowed {list(MODELS)}")
        lanes = [model != "velocity" and follows_lanes(obj) for obj in objects]
        if model == "lanes_or_velocity":
            objects = objects + [obj for obj, along in zip(objects, lanes) if along]
            lanes = lanes + [False] * (len(objects) - len(lanes))
        self.count = len(objects)
        self.lengths = np.array([float(o.LENGTH) for o in objects])
        self.widths = np.array([float(o.WIDTH) for o in objects])
        self.speeds = np.array([float(getattr(o, "speed", 0.0)) for o in objects])
        times = np.arange(steps * substeps + 1) * (dt / substeps)  # every sub-step's instant
        start = np.array([o.position for o in objects], float).reshape(self.count, 2)
        heading = np.array([float(o.heading) for o in objects])
        direction = np.stack([np.cos(heading), np.sin(heading)], -1)
        # every one at its velocity (a static object: 0), then the lane followers along their paths
        self.positions = start[None] + times[:, None, None] * (self.speeds[:, None] * direction)[None]
        self.headings = np.broadcast_to(heading, (len(times), self.count)).copy()
        fine, coarse = np.arange(len(times)) / substeps, np.arange(steps + 1)  # in forecast steps
        for m in np.flatnonzero(lanes):
            path, path_heading = cached_path(objects[m], dt, steps)
            self.positions[:, m, 0] = np.interp(fine, coarse, path[:, 0])
            self.positions[:, m, 1] = np.interp(fine, coarse, path[:, 1])
            self.headings[:, m] = np.interp(fine, coarse, path_heading)
        velocities = self.speeds[None, :, None] * np.stack([np.cos(self.headings), np.sin(self.headings)], -1)
        # Python rows: the contact test reads a few road users a sub-step, where numpy's call overhead dominates;
        # the standing ones (most of them: cones, broken-down cars) once, the moving ones at every sub-step
        sizes = list(zip(self.lengths.tolist(), self.widths.tolist(), np.abs(self.speeds).tolist()))
        moving = np.flatnonzero(self.speeds != 0.0)
        self._static = [(tuple(start[m]), float(heading[m]), *sizes[m]) for m in np.flatnonzero(self.speeds == 0.0)]
        self._moving = (moving, [sizes[m] for m in moving], velocities[:, moving])
        self._rows: list = [None] * len(times)  # built on first use: most forecasts end before the horizon
        # bounding boxes (x min, y min, x max, y max) and the largest half size and speed: most sub-steps have
        # nothing near the ego, and one box test says so
        half = (self.lengths + self.widths) / 2
        self._static_box = _box(start[self.speeds == 0.0][None])[0], float(half[self.speeds == 0.0].max(initial=0.0))
        self._moving_box = _box(self.positions[:, moving]), float(half[moving].max(initial=0.0)), \
            float(np.abs(self.speeds[moving]).max(initial=0.0))

    def _row(self, k: int) -> list:
        """The moving road users after sub-step ``k`` as Python tuples ``(point, heading, length, width, speed,
        velocity)``."""
        row = self._rows[k]
        if row is None:
            moving, sizes, velocities = self._moving
            row = self._rows[k] = [(point, heading, *size, velocity) for point, heading, size, velocity in zip(
                self.positions[k, moving].tolist(), self.headings[k, moving].tolist(), sizes,
                velocities[k].tolist())]
        return row

    def near(self, k: int, position, reach: float, speed_dt: float, dt: float) -> list:
        """The road users after sub-step ``k`` (clipped to the horizon) whose centre is within ``reach`` plus half
        their length and width plus their travel over ``dt`` of ``position``, ``speed_dt`` the ego's travel:
        ``[(position (2,), heading, length, width, velocity (2,))]``."""
        x, y = float(position[0]), float(position[1])
        k = min(k, len(self._rows) - 1)
        out = []
        box, half = self._static_box
        if _in_box(box, x, y, reach + half + speed_dt):
            for point, heading, length, width, _ in self._static:
                if math.hypot(point[0] - x, point[1] - y) <= reach + (length + width) / 2 + speed_dt:
                    out.append((np.array(point), heading, length, width, np.zeros(2)))
        boxes, half, speed_max = self._moving_box
        if _in_box(boxes[k], x, y, reach + half + speed_dt + speed_max * dt):
            for point, heading, length, width, speed, velocity in self._row(k):
                if math.hypot(point[0] - x, point[1] - y) <= reach + (length + width) / 2 + speed_dt + speed * dt:
                    out.append((np.array(point), heading, length, width, np.array(velocity)))
        return out

    def clear_of(self, position, reach: float, k: int, dt: float) -> bool:
        """Whether no moving road user comes within ``reach`` plus its half length and width plus its travel over
        ``dt`` of ``position`` after sub-step ``k`` (a box test: True is sure, False may be a near miss): a car
        standing there is safe for the rest of the forecast."""
        boxes, half, speed_max = self._moving_box
        x, y, margin = float(position[0]), float(position[1]), reach + half + speed_max * dt
        return not any(_in_box(box, x, y, margin) for box in boxes[k:])


def _box(points: np.ndarray) -> list:
    """``[(x min, y min, x max, y max)]`` of ``points`` ``(K, M, 2)`` per row (empty rows: a box nothing is in)."""
    if points.shape[1] == 0:
        return [(math.inf, math.inf, -math.inf, -math.inf)] * len(points)
    return np.concatenate([points.min(1), points.max(1)], -1).tolist()


def _in_box(box, x: float, y: float, margin: float) -> bool:
    return box[0] - margin <= x <= box[2] + margin and box[1] - margin <= y <= box[3] + margin


__all__ = ["MODELS", "RoadUsers", "cached_path", "follows_lanes", "lane_following_path"]
