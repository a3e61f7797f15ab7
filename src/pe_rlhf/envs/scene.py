"""Scenes from seeds: a route of blocks, static obstacles and background traffic.

``generate_scene(seed, config)`` is a pure function of its arguments: the same
seed and config give the same road, obstacles and vehicles. The result is a
:class:`Scene` blueprint; :meth:`Scene.populate` places fresh objects on a road.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pe_rlhf.envs.blocks import BLOCK_BUILDERS, ROAD_SPEED, Junction, RouteBuilder
from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.envs.fast_road import FastRoadNetwork
from pe_rlhf.envs.route import Route
from pe_rlhf.envs.traffic import BrokenDownCar, TrafficCar, TrafficCone, TrafficTruck, WarningTriangle

EGO_START = 10.0  # [m] along the first segment
EGO_SPEED = 8.0  # [m/s] initial ego speed
MIN_CLEARANCE = 7.0  # [m] between lanes of non-adjacent blocks


@dataclass(frozen=True)
class ObstacleSpec:
    kind: type
    lane_index: tuple
    longitudinal: float
    lateral: float = 0.0


@dataclass(frozen=True)
class VehicleSpec:
    kind: type
    lane_index: tuple
    longitudinal: float
    speed: float
    target_speed: float
    destination: str


@dataclass
class Scene:
    """The blueprint of one scene: road network, ego route, obstacles and traffic."""

    seed: int
    network: FastRoadNetwork
    route: Route
    blocks: list[str]
    obstacles: list[ObstacleSpec]
    vehicles: list[VehicleSpec]
    junctions: list[Junction] = field(default_factory=list)
    obstacle_events: list[tuple[str, int, float]] = field(default_factory=list)  # (kind, lane, route s)

    def populate(self, road) -> None:
        """Put fresh obstacles and traffic for this scene on ``road`` (whose network is ours)."""
        for j in self.junctions:
            j.occupant = None
        for spec in self.obstacles:
            lane = self.network.get_lane(spec.lane_index)
            obj = spec.kind(road, lane.position(spec.longitudinal, spec.lateral), lane.heading_at(spec.longitudinal))
            road.objects.append(obj)
        for spec in self.vehicles:
            lane = self.network.get_lane(spec.lane_index)
            v = spec.kind(road, lane.position(spec.longitudinal, 0), lane.heading_at(spec.longitudinal), spec.speed,
                          target_speed=spec.target_speed)
            v.plan_route_to(spec.destination)
            road.vehicles.append(v)


def _block_points(network: FastRoadNetwork, nodes: set[str]) -> np.ndarray:
    """Centre-line samples every 4 m of the lanes ending at ``nodes`` (the lanes a block added)."""
    pts = []
    for _from, to_dict in network.graph.items():
        for _to, lanes in to_dict.items():
            if _to in nodes:
                for lane in lanes:
                    for s in np.arange(0, lane.length, 4.0):
                        pts.append(lane.position(s, 0))
    return np.array(pts).reshape(-1, 2)


def _nodes(network: FastRoadNetwork) -> set[str]:
    return {n for f, t in network.graph.items() for n in [f, *t]}


def _build_route(rng: np.random.Generator, config: DrivingConfig) -> tuple[RouteBuilder, list[str]]:
    """Chain random blocks; reject a layout whose blocks overlap (retry with the same rng).

    A block may touch the block before it; it must keep ``MIN_CLEARANCE`` plus a lane
    width from every older block (its own lanes and side roads included).
    """
    for _ in range(50):
        b = RouteBuilder(lanes=config.lanes)
        b.straight(40.0, tag="s", obstacles_ok=False)
        names = list(rng.choice(config.block_types, size=int(rng.integers(config.min_blocks, config.max_blocks + 1))))
        blocks: list[set[str]] = [_nodes(b.network)]
        ok = True
        for name in names:
            before = _nodes(b.network)
            BLOCK_BUILDERS[name](b, rng)
            created = _nodes(b.network) - before
            pts = _block_points(b.network, created)
            old_pts = _block_points(b.network, set().union(*blocks[:-1])) if len(blocks) > 1 else np.zeros((0, 2))
            if len(old_pts) and len(pts):
                d = np.linalg.norm(pts[:, None, :] - old_pts[None, :, :], axis=2)
                if d.min() < MIN_CLEARANCE + 4.0:
                    ok = False
                    break
            blocks.append(created)
            if abs(math.degrees(b.pose.heading)) > 120:
                ok = False
                break
        if ok:
            b.straight(40.0, tag="d", obstacles_ok=False)
            return b, [str(n) for n in names]
    raise RuntimeError("could not lay out a non-overlapping route in 50 tries")


def _place_obstacles(b: RouteBuilder, route: Route, rng: np.random.Generator, config: DrivingConfig):
    specs, events = [], []
    lengths = np.array([route.segment_length(seg) for seg in b.obstacle_segments])
    if not len(lengths):
        return specs, events
    n_events = rng.poisson(config.obstacle_density * lengths.sum() / 100.0)
    taken: list[float] = []
    for _ in range(n_events):
        k = int(rng.choice(len(lengths), p=lengths / lengths.sum()))
        seg = b.obstacle_segments[k]
        if lengths[k] < 30:
            continue
        s = float(rng.uniform(15.0, lengths[k] - 10.0))
        s_route = route.segment_start(seg) + s
        if any(abs(s_route - t) < 40.0 for t in taken):
            continue
        taken.append(s_route)
        lane_id = int(rng.integers(0, config.lanes))
        ref = route.reference_lane(seg)
        lane_index = (*seg, lane_id)
        lane = b.network.get_lane(lane_index)
        s_lane = s * lane.length / ref.length  # same fraction along an inner/outer arc
        if rng.random() < 0.6:
            specs.append(ObstacleSpec(BrokenDownCar, lane_index, s_lane, float(rng.uniform(-0.4, 0.4))))
            specs.append(ObstacleSpec(WarningTriangle, lane_index, max(s_lane - 15.0, 0.5)))
            events.append(("broken_down", lane_id, s_route))
        else:
            side = rng.choice([-1.0, 1.0])
            for i in range(4):  # a taper across the lane, kept 1 m inside its edges
                specs.append(ObstacleSpec(TrafficCone, lane_index, s_lane + 2.5 * i, side * (0.9 - i * 0.6)))
            events.append(("cones", lane_id, s_route))
    return specs, events


def _place_traffic(b: RouteBuilder, route: Route, events, rng: np.random.Generator, config: DrivingConfig):
    specs: list[VehicleSpec] = []
    # Occupied positions per lane slot in route metres (so spacing holds across segment
    # boundaries), or per side lane in lane metres.
    occupied: dict[object, list[float]] = {}

    def free(key, s, gap=14.0) -> bool:
        return all(abs(s - o) > gap for o in occupied.get(key, []))

    def add(key, lane_index, s_key, s, dest, speed_limit):
        kind = TrafficTruck if rng.random() < config.truck_fraction else TrafficCar
        target = float(rng.uniform(0.7, 1.0) * speed_limit)
        specs.append(VehicleSpec(kind, lane_index, s, float(rng.uniform(0.7, 0.95)) * target, target, dest))
        occupied.setdefault(key, []).append(s_key)

    for seg in route.segments:
        ref = route.reference_lane(seg)
        for lane_id in range(min(config.lanes, len(b.network.graph[seg[0]][seg[1]]))):
            lane_index = (*seg, lane_id)
            lane = b.network.get_lane(lane_index)
            for _ in range(rng.poisson(config.traffic_density * lane.length / 100.0)):
                s = float(rng.uniform(0, lane.length))
                s_route = route.segment_start(seg) + s * ref.length / lane.length
                if s_route < EGO_START + 25.0 or not free(lane_id, s_route):
                    continue
                # Keep clear of obstacle events: a triangle 15 m before a car, or 7.5 m of cones
                # after the event point, plus the queue they cause before them.
                if any(e_lane == lane_id and -15.0 < e_s - s_route < 50.0 for _, e_lane, e_s in events):
                    continue
                dest = route.final_node
                if b.exits and rng.random() < 0.25:
                    exit_node = str(rng.choice(b.exits))
                    if b.network.shortest_path(seg[1], exit_node):
                        dest = exit_node  # leaves the route at a ramp or junction arm downstream
                add(lane_id, lane_index, s_route, s, dest, min(ROAD_SPEED, lane.speed_limit))
    for spawn in b.side_spawns:
        if rng.random() < config.side_traffic_probability and free(spawn.lane_index, spawn.longitudinal):
            dest = route.final_node if spawn.destination == "@route_end" else spawn.destination
            add(spawn.lane_index, spawn.lane_index, spawn.longitudinal, spawn.longitudinal, dest,
                b.network.get_lane(spawn.lane_index).speed_limit)
    return specs


def generate_scene(seed: int, config: DrivingConfig) -> Scene:
    """The scene of ``seed`` under ``config`` (deterministic)."""
    rng = np.random.default_rng([int(seed), 20240607])
    b, names = _build_route(rng, config)
    route = Route(b.network, b.segments, config.lanes)
    obstacles, events = _place_obstacles(b, route, rng, config)
    vehicles = _place_traffic(b, route, events, rng, config)
    return Scene(int(seed), b.network, route, names, obstacles, vehicles, b.junctions, events)
