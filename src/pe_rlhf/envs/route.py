"""The ego's route: ordered road segments, progress along them, checkpoints.

Progress is measured on each segment's *reference lane* (the middle lane of the
route's through lanes), the way MetaDrive measures ``d_t`` for its driving reward.
"""

from __future__ import annotations

import numpy as np
from highway_env.road.lane import AbstractLane

from pe_rlhf.envs.fast_road import FastRoadNetwork


class Route:
    """Ordered segments ``(from, to)`` the ego must drive, with cumulative lengths."""

    def __init__(self, network: FastRoadNetwork, segments: list[tuple[str, str]], lanes: int):
        if not segments:
            raise ValueError("a route needs at least one segment")
        self.network = network
        self.segments = list(segments)
        self.lanes = lanes
        self._ref = [network.get_lane((f, t, lanes // 2)) for f, t in self.segments]
        lengths = np.array([lane.length for lane in self._ref])
        self._starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self.length = float(lengths.sum())
        self._index = {seg: i for i, seg in enumerate(self.segments)}

    @property
    def final_node(self) -> str:
        return self.segments[-1][1]

    def reference_lane(self, segment: tuple[str, str]) -> AbstractLane:
        return self._ref[self._index[tuple(segment[:2])]]

    def segment_length(self, segment: tuple[str, str]) -> float:
        return float(self.reference_lane(segment).length)

    def segment_start(self, segment: tuple[str, str]) -> float:
        return float(self._starts[self._index[tuple(segment[:2])]])

    def segment_index(self, lane_index) -> int | None:
        """Index of the route segment a lane belongs to, or None (side road, arm, ramp)."""
        return self._index.get(tuple(lane_index[:2])) if lane_index else None

    def project(self, position: np.ndarray, hint: int) -> tuple[int, float]:
        """``(segment index, route progress [m])`` of ``position``, searching from segment ``hint``.

        Moves forward (or back) across segment ends, so a vehicle driving the route
        keeps a continuous progress even off its reference lane.
        """
        k = int(np.clip(hint, 0, len(self.segments) - 1))
        for _ in range(len(self.segments)):
            s, _ = self._ref[k].local_coordinates(position)
            if s > self._ref[k].length and k + 1 < len(self.segments):
                k += 1
            elif s < 0 and k > 0 and self._ref[k - 1].local_coordinates(position)[0] <= self._ref[k - 1].length:
                k -= 1
            else:
                break
        s = float(np.clip(s, 0.0, self._ref[k].length))
        return k, float(self._starts[k] + s)

    def lateral_offset(self, position: np.ndarray, k: int) -> float:
        """Signed lateral distance [m] from segment ``k``'s reference lane centre."""
        return float(self._ref[k].local_coordinates(position)[1])

    def heading_at(self, position: np.ndarray, k: int) -> float:
        lane = self._ref[k]
        s, _ = lane.local_coordinates(position)
        return float(lane.heading_at(float(np.clip(s, 0.0, lane.length))))

    def checkpoints(self, k: int, count: int = 2) -> list[np.ndarray]:
        """World positions of the ends of segments ``k .. k+count-1`` (the last repeats)."""
        out = []
        for i in range(count):
            j = min(k + i, len(self.segments) - 1)
            out.append(self._ref[j].position(self._ref[j].length, 0.0))
        return out
