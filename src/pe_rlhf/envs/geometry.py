"""Lane geometry for multi-lane roads: straight and arc segments built from a pose.

A :class:`Pose` is a point on a road's **left edge** (lateral 0 of lane 0's left
boundary) and a heading. Lanes are numbered from that edge towards the +lateral
side ``n = (-sin h, cos h)``, highway-env's convention (lane index grows to the
"right" on screen, where y points down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, StraightLane

LANE_WIDTH = 4.0


@dataclass(frozen=True)
class Pose:
    """A point on a road's left edge and the road heading there [m, m, rad]."""

    x: float
    y: float
    heading: float

    @property
    def point(self) -> np.ndarray:
        return np.array([self.x, self.y])

    @property
    def direction(self) -> np.ndarray:
        return np.array([math.cos(self.heading), math.sin(self.heading)])

    @property
    def lateral(self) -> np.ndarray:
        return np.array([-math.sin(self.heading), math.cos(self.heading)])

    def lane_point(self, lane: float, width: float = LANE_WIDTH) -> np.ndarray:
        """Centre of lane ``lane`` (may be fractional) at this pose."""
        return self.point + (lane + 0.5) * width * self.lateral

    def advanced(self, distance: float, lateral: float = 0.0) -> Pose:
        p = self.point + distance * self.direction + lateral * self.lateral
        return Pose(float(p[0]), float(p[1]), self.heading)


def _line_types(index: int, lanes: int, edges: str = "continuous") -> tuple:
    if edges == "none":
        return (LineType.NONE, LineType.NONE)
    left = LineType.CONTINUOUS_LINE if index == 0 else LineType.STRIPED
    right = LineType.CONTINUOUS_LINE if index == lanes - 1 else LineType.NONE
    return (left, right)


def straight_lanes(
    pose: Pose, length: float, lanes: int, speed_limit: float, edges: str = "continuous", first: int = 0
) -> tuple[list[AbstractLane], Pose]:
    """``lanes`` parallel straight lanes of ``length`` from ``pose``; returns (lanes, end pose).

    ``first`` offsets the lane positions (lane ``k`` of the list sits at lateral slot ``first + k``).
    """
    out = []
    for i in range(lanes):
        start = pose.lane_point(first + i)
        end = start + length * pose.direction
        out.append(
            StraightLane(start, end, LANE_WIDTH, _line_types(i, lanes, edges), speed_limit=speed_limit)
        )
    return out, pose.advanced(length)


def arc_lanes(
    pose: Pose,
    centre_radius: float,
    angle: float,
    lanes: int,
    speed_limit: float,
    edges: str = "continuous",
) -> tuple[list[AbstractLane], Pose]:
    """Concentric arc lanes turning by ``angle`` [rad] (positive towards +lateral).

    ``centre_radius`` is the radius of the road's centre line; returns (lanes, end pose).
    """
    if angle == 0:
        raise ValueError("arc angle must be non-zero")
    half_width = lanes * LANE_WIDTH / 2
    if centre_radius - half_width < 2.0:
        raise ValueError(f"centre_radius {centre_radius} too small for {lanes} lanes")
    out = []
    h = pose.heading
    if angle > 0:  # centre on the +lateral side, left edge is the outer edge
        r_left = centre_radius + half_width
        centre = pose.point + r_left * pose.lateral
        for i in range(lanes):
            r = r_left - (i + 0.5) * LANE_WIDTH
            out.append(
                CircularLane(centre, r, h - math.pi / 2, h - math.pi / 2 + angle, True, LANE_WIDTH,
                             _line_types(i, lanes, edges), speed_limit=speed_limit)
            )
        end_h = h + angle
        end = centre - r_left * np.array([-math.sin(end_h), math.cos(end_h)])
    else:  # centre on the -lateral side, left edge is the inner edge
        r_left = centre_radius - half_width
        centre = pose.point - r_left * pose.lateral
        for i in range(lanes):
            r = r_left + (i + 0.5) * LANE_WIDTH
            out.append(
                CircularLane(centre, r, h + math.pi / 2, h + math.pi / 2 + angle, False, LANE_WIDTH,
                             _line_types(i, lanes, edges), speed_limit=speed_limit)
            )
        end_h = h + angle
        end = centre + r_left * np.array([-math.sin(end_h), math.cos(end_h)])
    return out, Pose(float(end[0]), float(end[1]), end_h)


def turn_lane(
    start: np.ndarray, heading: float, radius: float, angle: float, speed_limit: float
) -> CircularLane:
    """A single arc lane starting at ``start`` (lane centre) with ``heading``, turning by ``angle``."""
    lat = np.array([-math.sin(heading), math.cos(heading)])
    if angle > 0:
        centre = start + radius * lat
        return CircularLane(centre, radius, heading - math.pi / 2, heading - math.pi / 2 + angle, True,
                            LANE_WIDTH, (LineType.NONE, LineType.NONE), speed_limit=speed_limit)
    centre = start - radius * lat
    return CircularLane(centre, radius, heading + math.pi / 2, heading + math.pi / 2 + angle, False,
                        LANE_WIDTH, (LineType.NONE, LineType.NONE), speed_limit=speed_limit)


def curve_speed(radius: float, lateral_acc: float = 2.5, cap: float = 15.0) -> float:
    """Speed limit [m/s] on an arc of ``radius`` for a comfortable lateral acceleration."""
    return float(min(cap, math.sqrt(lateral_acc * radius)))
