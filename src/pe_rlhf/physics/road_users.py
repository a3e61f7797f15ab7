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
velocity, 0.09 m and 1.3 m in this model (the rest its IDM acceleration). Its path is integrated once a forecast at
the forecast's step (0.1 s) and interpolated linearly for the sub-steps between; the forecasts of one decision share
it (:func:`cached_path`). Not forecast: a lane change the vehicle has not started yet (MOBIL), a change of speed
(the IDM: braking behind a queue or at a stop line, accelerating out of a bend), a crashed vehicle's stop. Every
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


class RoadUsers:
    """The road users ahead of the ego in one forecast, with their poses at every sub-step (module docstring).

    ``objects``: the highway-env vehicles and objects; ``dt`` [s] the forecast's step, ``steps`` its length in steps,
    ``substeps`` the simulator's sub-steps a step. :meth:`near` ``(k, ...)``: those near a point after sub-step ``k``
    (0: now); ``positions`` ``(K + 1, M, 2)`` and ``headings`` ``(K + 1, M)``: every one's pose at every sub-step."""

    def __init__(self, objects: list, dt: float, steps: int, substeps: int):
        self.count = len(objects)
        self.lengths = np.array([float(o.LENGTH) for o in objects])
        self.widths = np.array([float(o.WIDTH) for o in objects])
        self.speeds = np.array([float(getattr(o, "speed", 0.0)) for o in objects])
        self.moving = bool((self.speeds > 0.0).any())
        times = np.arange(steps * substeps + 1) * (dt / substeps)  # every sub-step's instant
        self.positions = np.empty((len(times), self.count, 2))
        self.headings = np.empty((len(times), self.count))
        for m, obj in enumerate(objects):
            position, heading = np.asarray(obj.position, float), float(obj.heading)
            if follows_lanes(obj):
                path, path_heading = cached_path(obj, dt, steps)
                fine = np.arange(len(times)) / substeps  # in forecast steps
                self.positions[:, m, 0] = np.interp(fine, np.arange(steps + 1), path[:, 0])
                self.positions[:, m, 1] = np.interp(fine, np.arange(steps + 1), path[:, 1])
                self.headings[:, m] = np.interp(fine, np.arange(steps + 1), path_heading)
            else:  # its velocity, kept (a static object: 0)
                velocity = self.speeds[m] * np.array([math.cos(heading), math.sin(heading)])
                self.positions[:, m] = position + times[:, None] * velocity
                self.headings[:, m] = heading
        velocities = self.speeds[None, :, None] * np.stack([np.cos(self.headings), np.sin(self.headings)], -1)
        # Python rows: the contact test reads a few road users a sub-step, where numpy's call overhead dominates
        self._rows = [list(zip(p.tolist(), h.tolist(), v.tolist())) for p, h, v in
                      zip(self.positions, self.headings, velocities)]
        self._sizes = list(zip(self.lengths.tolist(), self.widths.tolist(), self.speeds.tolist()))

    def near(self, k: int, position, reach: float, speed_dt: float, dt: float) -> list:
        """The road users after sub-step ``k`` (clipped to the horizon) whose centre is within ``reach`` plus half
        their length and width plus their travel over ``dt`` of ``position``, ``speed_dt`` the ego's travel:
        ``[(position (2,), heading, length, width, velocity (2,))]``."""
        x, y = float(position[0]), float(position[1])
        out = []
        for (point, heading, velocity), (length, width, speed) in zip(self._rows[min(k, len(self._rows) - 1)],
                                                                     self._sizes):
            if math.hypot(point[0] - x, point[1] - y) <= reach + (length + width) / 2 + speed_dt + speed * dt:
                out.append((np.array(point), heading, length, width, np.array(velocity)))
        return out


__all__ = ["RoadUsers", "cached_path", "follows_lanes", "lane_following_path"]
