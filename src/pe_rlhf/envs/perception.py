"""Route-frame (Frenet) view of the scene around the ego, for rule-based drivers.

Every nearby vehicle or obstacle is projected onto the ego's route: its progress
``s`` [m] along the route and its lane slot (0 = leftmost through lane). Gaps are
bumper to bumper. This reads the simulator's true state (privileged), which is what
the physics policy and the simulated mentors are allowed to see.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env import utils
from highway_env.vehicle.objects import Obstacle

from pe_rlhf.envs.geometry import LANE_WIDTH

LOOK_BEHIND = 60.0  # [m]
LOOK_AHEAD = 100.0  # [m]


@dataclass(frozen=True)
class Neighbour:
    """Another road user seen in the route frame."""

    obj: object
    s: float  # route progress of its centre [m]
    lane: int  # lane slot on the route
    lateral: float  # [m] signed offset from the route's reference lane centre
    speed: float  # along the route [m/s]
    length: float
    width: float
    is_obstacle: bool
    half_lateral: float  # [m] half of its extent across the route (an angled car is wider)


def ego_lane_slot(env) -> tuple[int, float]:
    """The ego's lane slot on the route and its offset [m] from that slot's centre."""
    lat = env.route.lateral_offset(env.vehicle.position, env.route_segment)
    slot_f = lat / LANE_WIDTH + env.route.lanes // 2
    slot = int(np.clip(np.round(slot_f), 0, env.route.lanes - 1))
    return slot, (slot_f - slot) * LANE_WIDTH


def neighbours(env, include_obstacles: bool = True, radius: float = LOOK_AHEAD) -> list[Neighbour]:
    """Vehicles (and, if asked, obstacles) within ``radius`` of the ego, in the route frame."""
    ego, route = env.vehicle, env.route
    k = env.route_segment
    out = []
    candidates = [v for v in env.road.vehicles if v is not ego]
    if include_obstacles:
        candidates += list(env.road.objects)
    for obj in candidates:
        if np.linalg.norm(obj.position - ego.position) > radius:
            continue
        j, s = route.project(obj.position, k)
        lat = route.lateral_offset(obj.position, j)
        if abs(lat) > (route.lanes / 2 + 0.5) * LANE_WIDTH + 2.0:
            continue  # on a side road or arm, not on the route's lanes
        slot = int(np.round(lat / LANE_WIDTH + route.lanes // 2))
        heading_diff = utils.wrap_to_pi(obj.heading - route.heading_at(obj.position, j))
        half_lateral = 0.5 * (obj.LENGTH * abs(np.sin(heading_diff)) + obj.WIDTH * abs(np.cos(heading_diff)))
        out.append(Neighbour(obj, s, slot, lat, float(obj.speed * np.cos(heading_diff)),
                             float(obj.LENGTH), float(obj.WIDTH), isinstance(obj, Obstacle), float(half_lateral)))
    return out


def occupies(n: Neighbour, lane: int, lanes: int) -> bool:
    """Whether ``n``'s body overlaps lane slot ``lane`` (a car straddling two lanes blocks both)."""
    centre = (lane - lanes // 2) * LANE_WIDTH
    return abs(n.lateral - centre) < LANE_WIDTH / 2 + n.half_lateral - 0.3


def leader_and_follower(
    items: list[Neighbour], lane: int, s: float, lanes: int
) -> tuple[Neighbour | None, Neighbour | None]:
    """Closest road user ahead of and behind route progress ``s`` that occupies lane slot ``lane``."""
    lead = follow = None
    for n in items:
        if not occupies(n, lane, lanes):
            continue
        if n.s >= s and (lead is None or n.s < lead.s):
            lead = n
        elif n.s < s and (follow is None or n.s > follow.s):
            follow = n
    return lead, follow
