"""A physics forecast of what an action leads to: seconds until a crash or leaving the road.

The value estimator of the hybrid selector must know that an action is *bad*, and a value fitted on
crash-free driving (or an expert's critics, which assume the expert's own continuation) does not. This
module predicts it from the vehicle model instead: the ego, a kinematic bicycle (the same equations as the
simulator's ``highway_env`` vehicle), holds the candidate action for ``hold`` seconds, then recovers as well
as a car can: full braking, steering back along the route or with the wheels straight, or, where braking cannot
avoid a road user coming at the car, driving on ahead at full throttle along the route, whichever fails latest
(``recovery``, default ``"route_or_straight_or_ahead"``). A lane-following road user ahead drives on at constant speed
both along its planned lanes, steered by its own lane-keeping controller, and straight on at its velocity, a contact
with either path a contact (:mod:`pe_rlhf.physics.road_users`; ``road_users``, default ``"lanes_or_velocity"``:
a car in a bend, or turning off at a junction or a roundabout, is forecast there, and the straight path stands in
for a lane change no model here foresees); any other road user keeps its velocity and static obstacles stay;
moving road users behind drive on along their route under the IDM, braking for the ego where highway-env's IDM
does and no harder than their car can (:mod:`pe_rlhf.physics.followers`; ``followers=False``: ignored); one behind
that is not a lane-following IDM vehicle moves as the road users ahead (it would not brake for the ego). A standing
ego is safe only while no moving road user can reach it: the forecast runs on until none can.
The forecast moves in the simulator's sub-steps (``1 / simulation_frequency``), and the candidate *fails* at
the first step where, after one of them, its body touches a road user by the simulator's own test (the polygon
test with each body pushed on by its velocity over the sub-step, which the env counts as a crash), or where its
centre leaves the road (the env's own ``is_on_road`` test and edge margin, once a step as the env).

:func:`time_to_failure` returns that instant in seconds (``horizon`` when nothing fails), so larger is
safer and a failure now is worth the least. :class:`SafetyForecastValue` scores a batch of actions with it
for :class:`~pe_rlhf.transforms.HybridActionSelector` (``selector.value=forecast``): the mentor's action
is executed unless it fails sooner than physics' by ``epsilon_select`` seconds or more.

It reads the simulator's true state (privileged), as the physics policy and the simulated mentors do.
A road user behind is a driver who brakes for the ego, which a constant-velocity forecast would not know;
ignoring it (as before ``followers``) judged hard braking in front of a fast follower safe.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import weakref
from dataclasses import dataclass

import numpy as np
import torch
from highway_env import utils

from pe_rlhf.envs.action import MAX_ACCELERATION, MAX_BRAKING, MAX_STEERING, action_to_controls, controls_to_action
from pe_rlhf.envs.driving_env import ROAD_EDGE_MARGIN  # the env's own off-road test, not a copy of it
from pe_rlhf.envs.geometry import LANE_WIDTH
from pe_rlhf.physics.followers import Followers, is_lane_follower
from pe_rlhf.physics.road_users import MODELS as ROAD_USER_MODELS
from pe_rlhf.physics.road_users import RoadUsers

NEAR = 60.0  # [m] road users nearer than this are always forecast
BODY_MARGIN = 10.0  # [m] more than the two bodies' half-lengths together
RECOVERY_STEERING_GAIN = 1.5  # [rad of wheel angle per rad of heading error] while recovering
# The recoveries after the hold. Full braking: "route" steers back along the route's heading (one recovery);
# "route_or_straight" also tries the wheels straight and keeps the better (steering back towards the route can
# steer into a road user beside the car); "lanes" tracks the centre of the lane the car is nearest to, or of either
# neighbour, and keeps the best (a lane change in progress is finished or undone, whichever is safer).
# "route_or_straight_or_ahead" adds driving on ahead, full throttle steering along the route, tried only where both
# braking recoveries fail: a car standing across a roundabout's ring or a junction is hit by a road user that does
# not brake for it, whatever it brakes, and can only get out of the way.
RECOVERIES = ("route", "route_or_straight", "route_or_straight_or_ahead", "lanes")
AHEAD = "ahead"  # the recovery mode that drives on (the others brake)
LANE_TAU_LATERAL = 0.6  # [s] lateral-offset loop of the lane recovery (the privileged driver's)
LANE_TAU_HEADING = 0.2  # [s] heading loop of the lane recovery
LANE_MAX_HEADING_OFFSET = math.pi / 8  # [rad] largest angle to the lane taken to reach its centre


@dataclass(frozen=True)
class SafetyForecastConfig:
    """``hold`` [s]: the candidate action is held this long; ``horizon`` [s]: the forecast's length;
    ``dt`` [s]: its integration step (``horizon`` 6 s: the action held 1 s, then a full stop from the top speed,
    30 m/s at 6 m/s^2; a 3 s forecast read never-brake at 108 km/h safe until braking could no longer stop it,
    docs/experiments/shield-calibration.md); ``recovery_braking`` [m/s^2]: deceleration after ``hold``;
    ``recovery``: the recovery's steering (``RECOVERIES``); ``hold_one_lane``: the hold ends once the car has moved
    one lane sideways;
    ``followers``: moving road users behind the ego drive on under the IDM (False: they are ignored);
    ``road_users``: how a lane-following road user ahead moves (:data:`pe_rlhf.physics.road_users.MODELS`)."""

    hold: float = 1.0
    horizon: float = 6.0
    dt: float = 0.1
    recovery_braking: float = MAX_BRAKING
    recovery: str = "route_or_straight_or_ahead"
    hold_one_lane: bool = False
    followers: bool = True
    road_users: str = "lanes_or_velocity"

    def __post_init__(self) -> None:
        if self.road_users not in ROAD_USER_MODELS:
            raise ValueError(f"SafetyForecastConfig.road_users={self.road_users!r} is invalid: allowed "
                             f"{list(ROAD_USER_MODELS)}")
        if self.recovery not in RECOVERIES:
            raise ValueError(f"SafetyForecastConfig.recovery={self.recovery!r} is invalid: allowed {list(RECOVERIES)}")
        for name in ("hold", "horizon", "dt", "recovery_braking"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < 0:
                raise ValueError(f"SafetyForecastConfig.{name}={value!r} must be a finite number >= 0")
        if self.dt <= 0 or self.horizon <= 0:
            raise ValueError(f"SafetyForecastConfig dt={self.dt!r} and horizon={self.horizon!r} must be > 0")


def _others(env, horizon: float) -> list:
    """The road users whose motion does not depend on the ego (:class:`RoadUsers`): static objects and vehicles the
    ego can reach within ``horizon`` seconds, ahead of it or behind it without a lane-following IDM (those with one:
    :class:`Followers`). Reach: ``NEAR``, or farther where the ego at full throttle and the road user at its speed
    close more than that (at 30 m/s a standing obstacle 75 m ahead is one braking can still avoid)."""
    ego = env.vehicle
    candidates = [obj for obj in list(env.road.vehicles) + list(env.road.objects) if obj is not ego]
    if not candidates:
        return []
    rel = np.array([obj.position for obj in candidates], float) - np.asarray(ego.position, float)
    speeds = np.array([float(getattr(obj, "speed", 0.0)) for obj in candidates])
    ego_reach = (float(ego.speed) + MAX_ACCELERATION * horizon) * horizon
    near = np.hypot(rel[:, 0], rel[:, 1]) <= np.maximum(NEAR, ego_reach + np.abs(speeds) * horizon + BODY_MARGIN)
    behind = rel @ np.array([math.cos(ego.heading), math.sin(ego.heading)]) < 0
    # a driver behind brakes for us: Followers forecasts it; a road user behind without an IDM on a lane does not
    return [obj for obj, n, b in zip(candidates, near, behind)
            if n and not (b and float(getattr(obj, "speed", 0.0)) > 0.1 and is_lane_follower(obj))]


_ROAD_USERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # env -> (its road users' state, RoadUsers)


def _road_users(env, config: SafetyForecastConfig, steps: int, substeps: int) -> RoadUsers:
    """:class:`RoadUsers` of :func:`_others`, built once while their state (and the ego's, which selects them) is
    unchanged: the forecasts of one decision (each candidate, the recovery, the repeated action) share it."""
    objects = _others(env, config.horizon)
    key = (config.dt, steps, substeps, config.road_users, tuple(
        (id(o), float(o.position[0]), float(o.position[1]), float(o.heading), float(getattr(o, "speed", 0.0)),
         getattr(o, "target_lane_index", None), tuple(getattr(o, "route", None) or ())) for o in objects))
    hit = _ROAD_USERS.get(env)
    if hit is not None and hit[0] == key:
        return hit[1]
    users = RoadUsers(objects, config.dt, steps, substeps, config.road_users)
    _ROAD_USERS[env] = (key, users)
    return users


def time_to_failure(env, action, config: SafetyForecastConfig | None = None) -> float:
    """Seconds until ``action`` (normalised ``[steering, throttle]``), held ``config.hold`` s and followed by
    the best recovery (``config.recovery``), makes the ego of ``env`` (a ``DrivingEnv``, or a wrapper of one)
    hit a road user or leave the road; ``config.horizon`` when it does neither. 0.0 when the ego already has."""
    config = config or SafetyForecastConfig()
    env = getattr(env, "unwrapped", env)
    ego = env.vehicle
    forecast = _Forecast(env, config)
    steering, accel = action_to_controls(action)
    state = (np.array(ego.position, float), float(ego.heading), float(ego.speed), env.route_segment,
             forecast.behind0)
    hold_steps = min(int(round(config.hold / config.dt)), forecast.steps)
    lateral0 = env.route.lateral_offset(state[0], state[3]) if config.hold_one_lane else 0.0
    for i in range(1, hold_steps + 1):
        state, failed = forecast.step(state, steering, accel, i)
        if failed:
            return i * config.dt
        if config.hold_one_lane:
            segment, _ = env.route.project(state[0], state[3])
            state = _on_segment(state, segment)
            if abs(env.route.lateral_offset(state[0], segment) - lateral0) >= LANE_WIDTH:
                hold_steps = i  # one lane change done: a driver steers no further
                break
    return forecast.best_recovery(state, hold_steps)[0]


def _clip(value: float, limit: float) -> float:
    return min(max(float(value), -limit), limit)


def _on_segment(state, segment):
    """``state`` with the ego's route segment replaced."""
    return state[:3] + (segment,) + state[4:]


class _Forecast:
    """One forecast's fixed context: the ego's size, the road users that can matter, the route.

    A forecast state: ``(position, heading, speed, route segment, behind)``, ``behind`` the followers' state
    (:class:`~pe_rlhf.physics.followers.Followers`; None without followers)."""

    def __init__(self, env, config: SafetyForecastConfig):
        self.env, self.config, self.ego = env, config, env.vehicle
        self.steps = int(round(config.horizon / config.dt))
        self.followers = Followers(env, NEAR) if config.followers else None
        self.behind0 = self.followers.initial() if self.followers else None
        self.max_speed = float(getattr(self.ego, "MAX_SPEED", 40.0))
        # The simulator moves in sub-steps of 1 / simulation_frequency and tests contact after each one; the
        # forecast does the same, so a contact is found where the simulator finds it (and only there).
        frequency = (getattr(env, "config", None) or {}).get("simulation_frequency")
        self.substeps = max(1, int(round(config.dt * frequency))) if frequency else 1

    @functools.cached_property
    def others(self) -> RoadUsers:
        """The road users ahead and the static objects, their poses at every sub-step (built on first use: the
        progress forecast never needs them; the forecasts of one decision share them: :func:`_road_users`)."""
        return _road_users(self.env, self.config, self.steps, self.substeps)

    def step(self, state, steering: float, accel: float, i: int):
        """``(state, failed)`` after forecast step ``i`` (one ``dt``): :meth:`advance` in the simulator's
        sub-steps, each followed by its contact test (:meth:`touching`), then the road test at the step's end
        (the env's, once a step)."""
        dt = self.config.dt / self.substeps
        touched = False
        for j in range(1, self.substeps + 1):
            state = self.advance(state, steering, accel, dt)
            touched = touched or self.touching(state, (i - 1) * self.substeps + j, dt)
        return state, touched or not self.env.road.network.is_on_road(state[0], ROAD_EDGE_MARGIN)

    def advance(self, state, steering: float, accel: float, dt: float | None = None):
        """One ``dt`` (``config.dt`` by default) of the kinematic bicycle (the simulator's equations), and of the
        followers."""
        position, heading, speed, segment, behind = state
        dt, half = (self.config.dt if dt is None else dt), self.ego.LENGTH / 2
        if behind is not None:  # they react to where the ego is now, then all move (the simulator's order)
            behind = self.followers.step(behind, position, heading, speed, dt)
        beta = math.atan(0.5 * math.tan(steering))
        position = position + speed * np.array([math.cos(heading + beta), math.sin(heading + beta)]) * dt
        heading += speed * math.sin(beta) / half * dt
        speed = min(max(speed + accel * dt, 0.0), self.max_speed)
        return position, heading, speed, segment, behind

    def touching(self, state, k: int, dt: float) -> bool:
        """Whether the ego at ``state``, after the forecast's sub-step ``k`` (of ``dt`` seconds), touches a road user:
        the simulator's own test after each of its sub-steps (highway-env's ``are_polygons_intersecting``, each body
        pushed on by its velocity over ``dt``; a contact in that look-ahead is an ``impact``, which the env counts as
        a crash)."""
        position, heading, speed = state[0], state[1], state[2]
        ego = self.ego
        ego_corners = ego_on = None  # built only when a road user is near enough to touch (most steps: none)
        reach = (ego.LENGTH + ego.WIDTH) / 2
        candidates = self.others.near(k, position, reach, speed * dt, dt) if self.others.count else []
        if state[4] is not None:
            candidates += [pose for pose in self.followers.poses(state[4])
                           if math.hypot(pose[0][0] - position[0], pose[0][1] - position[1])
                           <= reach + (pose[2] + pose[3]) / 2 + (speed + math.hypot(*pose[4])) * dt]
        for other, head, length, width, vel in candidates:
            if ego_corners is None:
                ego_corners = utils.rect_corners(position, ego.LENGTH, ego.WIDTH, heading)
                ego_on = speed * dt * np.array([math.cos(heading), math.sin(heading)])
            touching, will_touch, _ = utils.are_polygons_intersecting(
                ego_corners, utils.rect_corners(other, length, width, head), ego_on, vel * dt)
            if touching or will_touch:
                return True
        return False

    def recovery_modes(self, state) -> list:
        """The recoveries tried from ``state`` (``config.recovery``), in order of preference, each braking fully with
        its steering: "route" (back along the route), "straight" (the wheels straight), or lane slots (towards a
        lane's centre); last, :data:`AHEAD`: full throttle, steering along the route."""
        if self.config.recovery == "route":
            return ["route"]
        if self.config.recovery == "route_or_straight":
            return ["route", "straight"]
        if self.config.recovery == "route_or_straight_or_ahead":
            return ["route", "straight", AHEAD]
        route = self.env.route
        lateral = route.lateral_offset(state[0], state[3])
        nearest = min(max(int(round(lateral / LANE_WIDTH + route.lanes // 2)), 0), route.lanes - 1)
        return [s for s in (nearest, nearest - 1, nearest + 1) if 0 <= s < route.lanes]

    def best_recovery(self, state, start: int) -> tuple[float, object]:
        """``(seconds to a failure, mode)`` of the recovery mode (:meth:`recovery_modes`) from ``state`` (forecast
        step ``start``) that fails latest; the first such on a tie (the full horizon ends the search)."""
        best, best_mode = -1.0, None
        for mode in self.recovery_modes(state):
            value = self.recover(state, start, mode)
            if value > best:
                best, best_mode = value, mode
            if best >= self.config.horizon:
                break
        return best, best_mode

    def recovery_controls(self, state, mode) -> tuple[float, float]:
        """``(steering angle, acceleration)`` of recovery ``mode`` at ``state``: full braking (full throttle for
        :data:`AHEAD`) with :meth:`recovery_steering`."""
        accel = MAX_ACCELERATION if mode == AHEAD else -self.config.recovery_braking
        return self.recovery_steering(state, mode), accel

    def recovery_steering(self, state, mode) -> float:
        """The recovery's steering: back along the route (``mode`` "route" or :data:`AHEAD`), the wheels straight
        ("straight"), or towards lane slot ``mode``'s centre (an int)."""
        if mode == "straight":
            return 0.0
        position, heading, speed, segment = state[:4]
        route = self.env.route
        ref = route.heading_at(position, segment)
        if mode not in ("route", AHEAD):
            target = (mode - route.lanes // 2) * LANE_WIDTH
            error = route.lateral_offset(position, segment) - target
            speed_c = max(speed, 2.0)
            offset = math.asin(_clip(-error / LANE_TAU_LATERAL / speed_c, 1.0))
            ref += _clip(offset, LANE_MAX_HEADING_OFFSET)
            rate = utils.wrap_to_pi(ref - heading) / LANE_TAU_HEADING
            slip = math.asin(_clip(self.ego.LENGTH / 2 / speed_c * rate, 1.0))
            return _clip(math.atan(2 * math.tan(slip)), MAX_STEERING)
        return _clip(RECOVERY_STEERING_GAIN * utils.wrap_to_pi(ref - heading), MAX_STEERING)

    def recover(self, state, start: int, mode) -> float:
        """Seconds to a failure while recovering with ``mode`` (:meth:`recovery_controls`) from ``state`` (step
        ``start`` of the forecast)."""
        config = self.config
        for i in range(start + 1, self.steps + 1):
            state = _on_segment(state, self.env.route.project(state[0], state[3])[0])
            state, failed = self.step(state, *self.recovery_controls(state, mode), i)
            if failed:
                return i * config.dt
            if mode != AHEAD and state[2] <= 0.0 and state[4] is None and self.others.clear_of(
                    state[0], (self.ego.LENGTH + self.ego.WIDTH) / 2, i * self.substeps, config.dt / self.substeps):
                return config.horizon  # stopped on the road, clear of everything, nothing moving near: safe
        return config.horizon


class SafetyForecastValue(torch.nn.Module):
    """A value source for :class:`~pe_rlhf.transforms.HybridActionSelector` from the physics forecast.

    ``values(observation, actions, env=env)`` returns ``(1, N)`` float32: :func:`time_to_failure` of each of
    the ``N`` actions ``(N, 2)`` from the current state of ``env`` (the observation is not read: the
    forecast reads the simulator). The selector's advantage is then seconds of safety, and
    ``epsilon_select`` a time: the mentor is trusted unless its action fails that much sooner than
    physics'. ``needs_env`` tells the selector to pass the simulator. A module without parameters, so
    checkpoints and weight pushes treat it as any value source.
    """

    needs_env = True

    def __init__(self, config: SafetyForecastConfig | None = None):
        super().__init__()
        self.config = config or SafetyForecastConfig()

    def values(self, observation: torch.Tensor, actions: torch.Tensor, env=None) -> torch.Tensor:
        return self._forecast(actions, env, self.config)

    def repeated_values(self, observation: torch.Tensor, actions: torch.Tensor, env=None) -> torch.Tensor:
        """As :meth:`values`, each action held for the whole horizon (no recovery): the action as a driver who
        repeats it at every step will execute it (``HybridActionSelector(persistence=...)``)."""
        config = dataclasses.replace(self.config, hold=self.config.horizon)
        return self._forecast(actions, env, config)

    def progress(self, observation: torch.Tensor, actions: torch.Tensor, env=None) -> torch.Tensor:
        """``(1, N)`` float32: metres along the route the ego makes holding each of the ``N`` actions ``(N, 2)``
        for ``hold`` seconds (the vehicle model alone: nothing is checked for failure). What a value of safety
        does not measure: a safe action can stop the car (``HybridActionSelector(progress_margin=...)``)."""
        if env is None:
            raise ValueError("SafetyForecastValue.progress needs env= (the simulator to forecast from)")
        sim = getattr(env, "unwrapped", env)
        forecast = _Forecast(sim, dataclasses.replace(self.config, followers=False))
        start = sim.route.project(sim.vehicle.position, sim.route_segment)
        steps = min(int(round(self.config.hold / self.config.dt)), forecast.steps)
        out = []
        for action in actions.reshape(-1, actions.shape[-1]).detach().cpu().numpy():
            if not np.all(np.isfinite(action)):
                out.append(-math.inf)
                continue
            steering, accel = action_to_controls(action)
            state = (np.array(sim.vehicle.position, float), float(sim.vehicle.heading), float(sim.vehicle.speed),
                     start[0], None)
            for _ in range(steps):
                state = forecast.advance(state, steering, accel)
            out.append(float(sim.route.project(state[0], start[0])[1] - start[1]))
        return torch.tensor([out], dtype=torch.float32)

    def speed(self, env=None) -> torch.Tensor:
        """``(1,)`` float32: the ego's speed [m/s] now (``HybridActionSelector(latch_release_speed=...)``)."""
        if env is None:
            raise ValueError("SafetyForecastValue.speed needs env= (the simulator to read)")
        return torch.tensor([float(getattr(env, "unwrapped", env).vehicle.speed)], dtype=torch.float32)

    def recovery_value(self, env=None) -> torch.Tensor:
        """``(1, 1)``: seconds until a failure when the recovery starts now (no hold; the action is not read):
        what any fallback that brakes at once can reach (``HybridActionSelector(reference=...)``)."""
        return self.recovery_value_and_action(env)[0]

    def recovery_action(self, env=None) -> torch.Tensor:
        """``(2,)`` float32: the first step of the best recovery from now (the recovery of ``config.recovery`` that
        fails latest, as :meth:`recovery_value` forecasts it): the action a fallback executes where physics' own is
        forecast worse."""
        return self.recovery_value_and_action(env)[1]

    def recovery_value_and_action(self, env=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(recovery_value (1, 1), recovery_action (2,))`` from one forecast (the selector needs both)."""
        if env is None:
            raise ValueError("SafetyForecastValue.recovery_value_and_action needs env= (the simulator to forecast "
                             "from)")
        sim = getattr(env, "unwrapped", env)
        forecast = _Forecast(sim, self.config)
        state = (np.array(sim.vehicle.position, float), float(sim.vehicle.heading), float(sim.vehicle.speed),
                 sim.route.project(sim.vehicle.position, sim.route_segment)[0], forecast.behind0)
        value, mode = forecast.best_recovery(state, 0)
        return (torch.tensor([[value]], dtype=torch.float32),
                torch.as_tensor(controls_to_action(*forecast.recovery_controls(state, mode))))

    @property
    def horizon(self) -> float:
        """The forecast's length [s]: the value of an action that fails within it is below this."""
        return float(self.config.horizon)

    @staticmethod
    def _forecast(actions: torch.Tensor, env, config: SafetyForecastConfig) -> torch.Tensor:
        if env is None:
            raise ValueError("SafetyForecastValue.values needs env= (the simulator to forecast from)")
        acts = actions.reshape(-1, actions.shape[-1]).detach().cpu().numpy()
        out = [time_to_failure(env, a, config) if np.all(np.isfinite(a)) else 0.0 for a in acts]
        return torch.tensor([out], dtype=torch.float32)


__all__ = ["SafetyForecastConfig", "SafetyForecastValue", "time_to_failure"]
