"""The flat observation vector: ego state, navigation, ego-frame lidar.

Layout of the float32 vector (length ``10 + beams``, 250 by default; 270 with lane features):

====================  ==========================================================
slice                 content
====================  ==========================================================
``[0]``               speed / 22.2 m/s (80 km/h), in [0, 1]
``[1]``               heading error to the route lane / (pi/2), in [-1, 1]
``[2]``               current steering command (normalised action), in [-1, 1]
``[3]``               lateral offset from the current lane centre / (lane width/2), in [-1, 1]
``[4]``               distance to the left road edge / 12 m, in [0, 1]
``[5]``               distance to the right road edge / 12 m, in [0, 1]
``[6:8]``             next checkpoint (end of the current route segment), ego frame
                      ``(forward, lateral)`` / 50 m, in [-1, 1]
``[8:10]``            the checkpoint after it, same units
``[10:10+beams]``     lidar: beam ``i`` at ego heading + 2*pi*i/beams, distance to the
                      first vehicle or obstacle / 50 m, in [0, 1] (1 = nothing)
``[10+beams:+20]``    only with ``DrivingConfig(lane_features=True)``: the per-lane summary
                      of :mod:`pe_rlhf.envs.lane_summary`
====================  ==========================================================

Road edges reach the agent through ``[4:6]``, not through the lidar (as in MetaDrive).
"""

from __future__ import annotations

import math

import numpy as np
from highway_env import utils

from pe_rlhf.envs.geometry import LANE_WIDTH

V_MAX = 80.0 / 3.6  # [m/s] the spec's v_max
EDGE_SCALE = 12.0  # [m]
NAV_SCALE = 50.0  # [m]
EGO_STATE_DIM = 6
NAV_DIM = 4
OBS_SLICES = {
    "speed": slice(0, 1),
    "heading_error": slice(1, 2),
    "steering": slice(2, 3),
    "lane_offset": slice(3, 4),
    "edge_distances": slice(4, 6),
    "navigation": slice(6, 10),
    "lidar": slice(10, None),
}


def observation_size(beams: int, lane_features: bool = False) -> int:
    """The observation's length: ``10 + beams``, plus 20 with ``lane_features``."""
    from pe_rlhf.envs.lane_summary import LANE_FEATURES

    return EGO_STATE_DIM + NAV_DIM + beams + LANE_FEATURES * bool(lane_features)


def road_edge_distances(network, lane_index, position: np.ndarray) -> tuple[float, float]:
    """Distances [m] from ``position`` to the left and right edges of the road holding ``lane_index``."""
    _from, _to, _ = lane_index
    lanes = network.graph[_from][_to]
    _, lat0 = lanes[0].local_coordinates(position)
    left = lat0 + lanes[0].width_at(0) / 2
    right = (len(lanes) - 0.5) * LANE_WIDTH - lat0
    return float(left), float(right)


def ego_frame(vector: np.ndarray, heading: float) -> np.ndarray:
    """Rotate a world-frame vector into the ego frame ``(forward, lateral)``."""
    c, s = math.cos(heading), math.sin(heading)
    return np.array([c * vector[0] + s * vector[1], -s * vector[0] + c * vector[1]])


def build_observation(env) -> np.ndarray:
    """Observation of ``env`` (a :class:`~pe_rlhf.envs.driving_env.DrivingEnv`) at its current state."""
    ego, route = env.vehicle, env.route
    k = env.route_segment
    lane = ego.lane
    s, lat = lane.local_coordinates(ego.position)
    heading_error = utils.wrap_to_pi(ego.heading - route.heading_at(ego.position, k))
    left, right = road_edge_distances(env.road.network, ego.lane_index, ego.position)
    nav = []
    for cp in route.checkpoints(k, 2):
        nav.extend(ego_frame(cp - ego.position, ego.heading) / NAV_SCALE)
    state = [
        ego.speed / V_MAX,
        heading_error / (math.pi / 2),
        env.last_action[0],
        lat / (lane.width_at(s) / 2),
        left / EDGE_SCALE,
        right / EDGE_SCALE,
    ]
    head = np.clip(np.array(state + nav, dtype=np.float32), -1.0, 1.0)
    head[0] = max(head[0], 0.0)
    head[4:6] = np.clip(head[4:6], 0.0, 1.0)
    objects = [v for v in env.road.vehicles if v is not ego] + env.road.objects
    lidar = env.lidar.scan_objects(ego, objects)
    if env.world.lane_features:
        from pe_rlhf.envs.lane_summary import lane_features

        return np.concatenate([head, lidar, lane_features(env, V_MAX)]).astype(np.float32)
    return np.concatenate([head, lidar]).astype(np.float32)
