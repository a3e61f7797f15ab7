"""Hand-built scenes on the real simulator for the physics, perception, forecast and disturbance tests: an empty
straight three-lane road (traffic, obstacles and side traffic switched off), a long straight road, and helpers
that place the ego, ``TrafficCar`` s and ``BrokenDownCar`` s. Lane slots: 0 = leftmost."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.envs.blocks import RouteBuilder
from pe_rlhf.envs.route import Route
from pe_rlhf.envs.scene import Scene
from pe_rlhf.envs.traffic import BrokenDownCar, TrafficCar

DT = 0.1  # [s] one policy step (policy_frequency = 10 Hz)
CAR_LENGTH = 4.5  # [m] ego and TrafficCar
EMPTY_STRAIGHT = dict(
    traffic_density=0, obstacle_density=0, side_traffic_probability=0,
    block_types=("straight",), min_blocks=2, max_blocks=2, split=None,
)
LONG_ROAD_SEED = 987_654_321  # cache key of the hand-built long road (never a generated seed)
CURVE_SEED = 987_654_322  # cache key of the hand-built bend


# --------------------------------------------------------------------------- scene helpers


def straight_env(scene_seed: int = 0):
    """The generated empty straight three-lane road (2 straight blocks, ~200-300 m)."""
    env = make_gym_env(DrivingConfig(**EMPTY_STRAIGHT))
    env.reset(options={"scene_seed": scene_seed})
    assert not env.road.objects and env.road.vehicles == [env.vehicle]
    return env


def long_road_scene(length: float) -> Scene:
    b = RouteBuilder(lanes=3)
    b.straight(40.0, tag="s", obstacles_ok=False)
    b.straight(length)
    b.straight(40.0, tag="d", obstacles_ok=False)
    return Scene(LONG_ROAD_SEED, b.network, Route(b.network, b.segments, 3), ["straight"], [], [])


def long_road_env(length: float = 900.0):
    """An empty straight three-lane road of ``length`` + 80 m.

    The generator cannot chain more than two straight blocks (see
    ``test_scene_generator_can_chain_straight_blocks``), and following a car for 40 s
    needs more road than two blocks give, so the scene is built here and put in the
    env's scene cache under a seed no generated scene uses.
    """
    env = make_gym_env(DrivingConfig(**EMPTY_STRAIGHT))
    env._scenes[LONG_ROAD_SEED] = long_road_scene(length)
    env.reset(options={"scene_seed": LONG_ROAD_SEED})
    assert env.route.length == pytest.approx(length + 80.0)
    return env


def curve_env(radius: float = 30.0, angle: float = math.pi / 2):
    """An empty three-lane road: 40 m straight, then a bend of ``radius`` [m] (the road's centre line) turning by
    ``angle`` [rad] (positive: towards lane slot 2, the inner lane), then 60 m straight; built here as
    :func:`long_road_env` is (the generator draws bends, it does not take them as arguments)."""
    b = RouteBuilder(lanes=3)
    b.straight(40.0, tag="s", obstacles_ok=False)
    b.arc(radius, angle, obstacles_ok=False)
    b.straight(60.0, tag="d", obstacles_ok=False)
    env = make_gym_env(DrivingConfig(**EMPTY_STRAIGHT))
    env._scenes[CURVE_SEED] = Scene(CURVE_SEED, b.network, Route(b.network, b.segments, 3), ["curve"], [], [])
    env.reset(options={"scene_seed": CURVE_SEED})
    return env


def lane_pose(env, s: float, lane: int) -> tuple[np.ndarray, float]:
    """World position and heading at route progress ``s`` [m], centre of lane slot ``lane``."""
    route = env.route
    for k, seg in enumerate(route.segments):
        start = route.segment_start(seg)
        if s <= start + route.segment_length(seg) or k == len(route.segments) - 1:
            lane_obj = env.road.network.get_lane((*seg, lane))
            return np.array(lane_obj.position(s - start, 0.0)), float(lane_obj.heading_at(s - start))
    raise AssertionError("unreachable")


def place_ego(env, s: float, lane: int = 1, speed: float = 8.0, lateral: float = 0.0, dheading: float = 0.0):
    """Move the ego to route progress ``s`` in ``lane`` (offset ``lateral`` m, heading error ``dheading``)."""
    pos, heading = lane_pose(env, s, lane)
    ego = env.vehicle
    ego.position = pos + lateral * np.array([-math.sin(heading), math.cos(heading)])
    ego.heading = heading + dheading
    ego.speed = speed
    ego.on_state_update()
    env.route_segment, env.progress = env.route.project(ego.position, 0)


def add_car(env, s: float, lane: int, speed: float, target_speed: float, cls=TrafficCar) -> TrafficCar:
    """A background car at route progress ``s`` in ``lane``, driving to the route end, never changing lane."""
    pos, heading = lane_pose(env, s, lane)
    car = cls(env.road, pos, heading, speed, target_speed=target_speed, enable_lane_change=False)
    car.plan_route_to(env.route.final_node)
    env.road.vehicles.append(car)
    return car


def add_obstacle(env, s: float, lane: int) -> BrokenDownCar:
    pos, heading = lane_pose(env, s, lane)
    obstacle = BrokenDownCar(env.road, pos, heading)
    env.road.objects.append(obstacle)
    return obstacle


def progress_of(env, obj) -> float:
    return env.route.project(obj.position, env.route_segment)[1]


def bumper_gap(env, leader) -> float:
    return progress_of(env, leader) - env.progress - (leader.LENGTH + env.vehicle.LENGTH) / 2


def drive(env, policy, steps: int, on_step=None):
    """Run ``policy`` for up to ``steps`` steps; returns (actions, last info, terminated).

    ``on_step(env, action, info)`` is called after every step.
    """
    actions, info, terminated = [], {}, False
    for _ in range(steps):
        action = policy(env)
        actions.append(np.asarray(action))
        _, _, terminated, truncated, info = env.step(action)
        if on_step is not None:
            on_step(env, action, info)
        if terminated or truncated:
            break
    return np.array(actions), info, terminated


def crossing_at_a_standing_ego(lateral: float = 15.0, speed: float = 6.0):
    """The ego standing in the middle lane; a plain highway-env vehicle (it keeps its velocity: a car on a
    roundabout's ring does not brake for a car standing across it) ``lateral`` metres to its left, 0.5 m ahead of
    its centre, driving across the ego's lane at ``speed``: it reaches the ego's side in about 2 s."""
    from highway_env.vehicle.kinematics import Vehicle

    env = straight_env(scene_seed=0)
    env.vehicle.speed = 0.0
    ego = env.vehicle
    forward = np.array([np.cos(ego.heading), np.sin(ego.heading)])
    left = np.array([np.sin(ego.heading), -np.cos(ego.heading)])  # towards lane slot 0
    env.road.vehicles.append(Vehicle(env.road, ego.position + 0.5 * forward + lateral * left,
                                     heading=ego.heading + np.pi / 2, speed=speed))
    return env
