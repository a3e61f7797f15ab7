"""Road blocks that chain into a route: straight, curve, on-ramp, off-ramp, roundabout, T-junction, 4-way.

Each block function extends a :class:`RouteBuilder` from its current end pose and
records what the scene generator needs: the ego's route segments, where side
traffic enters (with its destination), where traffic may leave, which segments
may hold static obstacles, and junction boxes where side traffic gives way.

Blocks are data-driven: ``BLOCK_BUILDERS[name](builder, rng)`` draws the block's
shape from ``rng``, so a scene is a function of its seed alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from highway_env.road.lane import AbstractLane, StraightLane

from pe_rlhf.envs.fast_road import FastRoadNetwork
from pe_rlhf.envs.geometry import LANE_WIDTH, Pose, arc_lanes, curve_speed, straight_lanes, turn_lane

ROAD_SPEED = 15.0  # [m/s] speed limit on straight route segments (54 km/h)
JUNCTION_SPEED = 8.0  # [m/s] inside junction boxes and on turning lanes
SIDE_SPEED = 10.0  # [m/s] on ramps and side arms

BLOCK_TYPES = ("straight", "curve", "on_ramp", "off_ramp", "roundabout", "t_junction", "intersection")


@dataclass
class Junction:
    """A conflict area where side traffic gives way to the route; one side vehicle at a time."""

    centre: np.ndarray
    radius: float
    occupant: object | None = None


@dataclass
class SideSpawn:
    """A place where side traffic enters: lane index, longitudinal position, destination node."""

    lane_index: tuple
    longitudinal: float
    destination: str


@dataclass
class RouteBuilder:
    """Accumulates the road network and the ego route while blocks are appended."""

    lanes: int = 3
    network: FastRoadNetwork = field(default_factory=FastRoadNetwork)
    pose: Pose = field(default_factory=lambda: Pose(0.0, 0.0, 0.0))
    segments: list[tuple[str, str]] = field(default_factory=list)
    obstacle_segments: list[tuple[str, str]] = field(default_factory=list)
    side_spawns: list[SideSpawn] = field(default_factory=list)
    exits: list[str] = field(default_factory=list)
    junctions: list[Junction] = field(default_factory=list)
    block_names: list[str] = field(default_factory=list)
    _count: int = 0

    @property
    def node(self) -> str:
        """The node at the current end of the route."""
        return self.segments[-1][1] if self.segments else "start"

    def new_node(self, tag: str) -> str:
        self._count += 1
        return f"{tag}{self._count}"

    def add_road(self, lanes: list[AbstractLane], end_pose: Pose, tag: str, obstacles_ok: bool = True) -> str:
        """Append lanes as the next route segment; returns its end node."""
        start, end = self.node, self.new_node(tag)
        for lane in lanes:
            self.network.add_lane(start, end, lane)
        self.segments.append((start, end))
        if obstacles_ok:
            self.obstacle_segments.append((start, end))
        self.pose = end_pose
        return end

    def straight(self, length: float, tag: str = "s", obstacles_ok: bool = True, speed: float = ROAD_SPEED) -> str:
        lanes, end = straight_lanes(self.pose, length, self.lanes, speed)
        return self.add_road(lanes, end, tag, obstacles_ok)

    def arc(self, radius: float, angle: float, tag: str = "c", obstacles_ok: bool = True) -> str:
        lanes, end = arc_lanes(self.pose, radius, angle, self.lanes, curve_speed(radius - LANE_WIDTH))
        return self.add_road(lanes, end, tag, obstacles_ok)



def build_straight(b: RouteBuilder, rng: np.random.Generator) -> None:
    b.straight(float(rng.uniform(60, 110)))


def build_curve(b: RouteBuilder, rng: np.random.Generator) -> None:
    angle = math.radians(rng.uniform(35, 90)) * rng.choice([-1, 1])
    b.arc(float(rng.uniform(35, 70)), angle)
    b.straight(20.0, obstacles_ok=False)


def build_on_ramp(b: RouteBuilder, rng: np.random.Generator) -> None:
    """Main road with an acceleration lane that a one-lane ramp feeds from the +lateral side."""
    b.straight(40.0)
    merge_start = b.pose
    accel_len = float(rng.uniform(60, 90))
    lanes, end = straight_lanes(merge_start, accel_len, b.lanes + 1, ROAD_SPEED)
    b.add_road(lanes, end, "m")
    ramp_end = merge_start.lane_point(b.lanes)
    ramp_dir = merge_start.heading - math.radians(15)  # comes in from the +lateral side
    ramp_start = ramp_end - 40.0 * np.array([math.cos(ramp_dir), math.sin(ramp_dir)])
    r0 = b.new_node("r")
    b.network.add_lane(r0, b.segments[-1][0], StraightLane(ramp_start, ramp_end, LANE_WIDTH, speed_limit=SIDE_SPEED))
    b.side_spawns.append(SideSpawn((r0, b.segments[-1][0], 0), float(rng.uniform(0, 15)), "@route_end"))
    b.straight(30.0)


def build_off_ramp(b: RouteBuilder, rng: np.random.Generator) -> None:
    """Main road with a deceleration lane that leaves to the +lateral side as a one-lane exit."""
    b.straight(30.0)
    lanes, end = straight_lanes(b.pose, float(rng.uniform(50, 70)), b.lanes + 1, ROAD_SPEED)
    fork = b.add_road(lanes, end, "f")
    exit_start = b.pose.lane_point(b.lanes)
    heading = b.pose.heading + math.radians(15)  # leaves towards +lateral
    exit_end = exit_start + 80.0 * np.array([math.cos(heading), math.sin(heading)])
    x1 = b.new_node("x")
    b.network.add_lane(fork, x1, StraightLane(exit_start, exit_end, LANE_WIDTH, speed_limit=SIDE_SPEED))
    b.exits.append(x1)
    b.straight(30.0)


def _junction(b: RouteBuilder, rng: np.random.Generator, sides: tuple[int, ...]) -> None:
    """A through junction box with one-lane arms on ``sides`` (+1: +lateral, -1: -lateral).

    Arms carry incoming traffic that gives way, then turns into the route or crosses;
    route traffic may turn off into outgoing arms.
    """
    b.straight(25.0, obstacles_ok=False)
    box_len = 22.0
    entry_pose = b.pose
    h = entry_pose.heading
    n_lanes = b.lanes
    box_lanes, end = straight_lanes(entry_pose, box_len, n_lanes, JUNCTION_SPEED, edges="none")
    box_end = b.add_road(box_lanes, end, "j", obstacles_ok=False)
    box_start = b.segments[-1][0]
    centre = entry_pose.point + box_len / 2 * entry_pose.direction + n_lanes * LANE_WIDTH / 2 * entry_pose.lateral
    junction = Junction(centre=centre, radius=box_len / 2 + n_lanes * LANE_WIDTH / 2)
    b.junctions.append(junction)
    r_out = 6.0
    for side in sides:
        edge_lane = n_lanes - 1 if side > 0 else 0
        # Incoming arm ends r_in before the box end and r_in outside the road edge, then
        # turns into the route; arms on the two sides join at different places so they never meet.
        r_in = 10.0 if side > 0 else 6.0
        join = end.lane_point(edge_lane)
        arm_end = join - r_in * entry_pose.direction + side * r_in * entry_pose.lateral
        arm_heading = h - side * math.pi / 2
        arm_start = arm_end - 45.0 * np.array([math.cos(arm_heading), math.sin(arm_heading)])
        a0, a1 = b.new_node("a"), b.new_node("a")
        arm = StraightLane(arm_start, arm_end, LANE_WIDTH, speed_limit=SIDE_SPEED)
        arm.junction = junction  # side traffic on this lane gives way
        b.network.add_lane(a0, a1, arm)
        b.network.add_lane(a1, box_end, turn_lane(arm_end, arm_heading, r_in, side * math.pi / 2, JUNCTION_SPEED))
        b.side_spawns.append(SideSpawn((a0, a1, 0), float(rng.uniform(0, 10)), "@route_end"))
        if len(sides) == 2 and side < 0:
            # Crossing traffic: straight over the box from the -lateral arm to the far side.
            k = b.new_node("k")
            far = arm_end + (n_lanes * LANE_WIDTH + 60.0) * entry_pose.lateral
            b.network.add_lane(a1, k, StraightLane(arm_end, far, LANE_WIDTH, speed_limit=JUNCTION_SPEED))
            b.side_spawns.append(SideSpawn((a0, a1, 0), float(rng.uniform(0, 10)), k))
            b.exits.append(k)
        # Outgoing arm: route traffic turns off from the edge lane at the box start.
        out_start = entry_pose.lane_point(edge_lane)
        o1, o2 = b.new_node("o"), b.new_node("o")
        turn = turn_lane(out_start, h, r_out, side * math.pi / 2, JUNCTION_SPEED)
        b.network.add_lane(box_start, o1, turn)
        turn_end = turn.position(turn.length, 0)
        b.network.add_lane(o1, o2, StraightLane(turn_end, turn_end + 40.0 * side * entry_pose.lateral,
                                                LANE_WIDTH, speed_limit=SIDE_SPEED))
        b.exits.append(o2)
    b.straight(25.0, obstacles_ok=False)


def build_t_junction(b: RouteBuilder, rng: np.random.Generator) -> None:
    _junction(b, rng, (int(rng.choice([-1, 1])),))


def build_intersection(b: RouteBuilder, rng: np.random.Generator) -> None:
    _junction(b, rng, (1, -1))


def build_roundabout(b: RouteBuilder, rng: np.random.Generator) -> None:
    """Enter a three-lane ring around a central island, follow it, leave.

    The route is an S of entry arc, ring arc and exit arc; the rest of the ring is
    drawn too (lanes from the exit point back round to the entry point), so ring
    traffic circulates and merges into the ego's part of the ring. ``net`` is the
    turn between entry and exit arms: 0 (straight over) or a quarter turn.
    """
    entry, ring_r = math.radians(40), float(rng.uniform(28, 36))
    net = math.radians(float(rng.choice([0, 90])))
    ring_angle = net + 2 * entry
    b.straight(15.0, obstacles_ok=False)
    b.arc(22.0, entry, tag="e", obstacles_ok=False)
    ring_start = b.node
    b.arc(ring_r, -ring_angle, tag="o", obstacles_ok=False)
    ring_end = b.node
    rest, _ = arc_lanes(b.pose, ring_r, -(2 * math.pi - ring_angle), b.lanes, curve_speed(ring_r - LANE_WIDTH))
    for lane in rest:
        b.network.add_lane(ring_end, ring_start, lane)
    for _ in range(int(rng.integers(1, 3))):
        lane_id = int(rng.integers(0, b.lanes))
        s = float(rng.uniform(0.2, 0.8) * rest[lane_id].length)
        b.side_spawns.append(SideSpawn((ring_end, ring_start, lane_id), s, "@route_end"))
    b.arc(22.0, entry, tag="e", obstacles_ok=False)
    b.straight(20.0, obstacles_ok=False)


BLOCK_BUILDERS = {
    "straight": build_straight,
    "curve": build_curve,
    "on_ramp": build_on_ramp,
    "off_ramp": build_off_ramp,
    "roundabout": build_roundabout,
    "t_junction": build_t_junction,
    "intersection": build_intersection,
}
