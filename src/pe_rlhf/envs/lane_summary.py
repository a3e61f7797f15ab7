"""Per-lane summary of the road users within the lidar's range: what the lidar holds, said per lane.

``DrivingConfig(lane_features=True)`` appends :func:`lane_features` to the observation. The lidar
gives distances by bearing; which lane a return lies in depends on the road's geometry (curves,
lane count), which a small network has to learn before it can tell "blocked ahead, free on the
left" from "a car in the next lane". Measured: a network imitating the professional from the raw
observation plateaus near half its success, and with these 20 numbers gets close to it
(``benchmarks/imitation_ceiling.py``, README "What limits imitation here"). Nothing here reaches
beyond ``LANE_RANGE`` (the lidar's 50 m), so the agent still perceives no more than its sensor.

Layout, float32 ``(20,)``:

==========  ================================================================================
index       content
==========  ================================================================================
``[0]``     the ego's lane slot / (lanes - 1) (0 = leftmost), in [0, 1]
``[1]``     lanes / 4
``[2:8]``   the lane left of the ego: exists, bumper gap to the first road user ahead / 50 m
            (1 = none within 50 m), its speed relative to the ego / v_max, it stands (an
            obstacle or a stopped car), gap to the first one behind / 50 m, its relative speed
``[8:14]``  the ego's lane, same six
``[14:20]`` the lane right of the ego, same six (an absent lane: all zeros)
==========  ================================================================================
"""

from __future__ import annotations

import numpy as np

LANE_RANGE = 50.0  # [m] the default lidar's range
LANE_FEATURES = 2 + 3 * 6


def lane_features(env, v_max: float) -> np.ndarray:
    """The table above for ``env`` (a :class:`~pe_rlhf.envs.driving_env.DrivingEnv`) now."""
    from pe_rlhf.envs.perception import ego_lane_slot, leader_and_follower, neighbours  # noqa: PLC0415

    items = neighbours(env, include_obstacles=True, radius=LANE_RANGE + 10.0)
    slot, _ = ego_lane_slot(env)
    lanes, s, ego = env.route.lanes, env.progress, env.vehicle
    out = [slot / max(lanes - 1, 1), lanes / 4.0]
    for lane in (slot - 1, slot, slot + 1):
        if not 0 <= lane < lanes:
            out += [0.0] * 6
            continue
        lead, follow = leader_and_follower(items, lane, s, lanes)
        ahead = 1.0 if lead is None else (lead.s - s - (lead.length + ego.LENGTH) / 2) / LANE_RANGE
        behind = 1.0 if follow is None else (s - follow.s - (follow.length + ego.LENGTH) / 2) / LANE_RANGE
        out += [1.0, float(np.clip(ahead, 0.0, 1.0)),
                0.0 if lead is None else float(np.clip((lead.speed - ego.speed) / v_max, -1.0, 1.0)),
                0.0 if lead is None else float(lead.is_obstacle or lead.speed < 1.0),
                float(np.clip(behind, 0.0, 1.0)),
                0.0 if follow is None else float(np.clip((follow.speed - ego.speed) / v_max, -1.0, 1.0))]
    return np.asarray(out, dtype=np.float32)
