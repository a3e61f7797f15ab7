"""A highway-env road that scales with the scene: spatial lane lookup and local interactions.

highway-env's stock ``Road`` does all-pairs Python searches (every vehicle against
every vehicle and object, every lane for the closest-lane lookup). Our routes hold
dozens of lanes and vehicles spread over half a kilometre, so:

- :class:`FastRoadNetwork` answers ``get_closest_lane_index`` from a bounding-box
  prefilter (exact same answer: the lanes it skips are farther than the best one);
- :class:`ActiveRoad` only steps vehicles within ``active_radius`` of the ego
  (frozen beyond it: they neither move nor interact until the ego comes near) and
  prefilters neighbour and collision searches by distance with numpy.
"""

from __future__ import annotations

import numpy as np
from highway_env.road.lane import AbstractLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.objects import Landmark

NEIGHBOUR_RADIUS = 120.0  # [m] farther vehicles have no IDM/MOBIL effect worth computing (s*/s < 0.1)


class FastRoadNetwork(RoadNetwork):
    """``RoadNetwork`` with a bounding-box index for the closest-lane lookup."""

    def __init__(self):
        super().__init__()
        self._index: tuple | None = None

    def add_lane(self, _from: str, _to: str, lane: AbstractLane) -> None:
        super().add_lane(_from, _to, lane)
        self._index = None

    def _build_index(self) -> tuple:
        keys, boxes = [], []
        for _from, to_dict in self.graph.items():
            for _to, lanes in to_dict.items():
                for _id, lane in enumerate(lanes):
                    s = np.linspace(0, lane.length, max(2, int(lane.length // 2) + 2))
                    pts = np.array([lane.position(si, 0) for si in s])
                    pad = lane.width_at(0) / 2
                    boxes.append([*(pts.min(0) - pad), *(pts.max(0) + pad)])
                    keys.append((_from, _to, _id))
        self._index = (keys, np.array(boxes))
        return self._index

    def get_closest_lane_index(self, position: np.ndarray, heading: float | None = None):
        keys, boxes = self._index or self._build_index()
        # A lane's distance is >= the point's distance to the lane's box, so lanes whose
        # box is farther than the best distance found cannot win: the answer is exact.
        margin, best, best_d = 1.0, None, np.inf
        while True:
            near = np.flatnonzero(
                (position[0] >= boxes[:, 0] - margin) & (position[0] <= boxes[:, 2] + margin)
                & (position[1] >= boxes[:, 1] - margin) & (position[1] <= boxes[:, 3] + margin)
            )
            for i in near:
                d = self.get_lane(keys[i]).distance_with_heading(position, heading)
                if d < best_d:
                    best, best_d = keys[i], d
            if best is not None and best_d <= margin:
                return best
            if len(near) == len(keys):
                return best
            margin = best_d if best is not None else margin * 8


    def is_on_road(self, position: np.ndarray, margin: float = 0.0) -> bool:
        """Whether ``position`` lies on some lane (within ``margin`` [m] beyond its edges)."""
        keys, boxes = self._index or self._build_index()
        near = np.flatnonzero(
            (position[0] >= boxes[:, 0] - margin) & (position[0] <= boxes[:, 2] + margin)
            & (position[1] >= boxes[:, 1] - margin) & (position[1] <= boxes[:, 3] + margin)
        )
        for i in near:
            lane = self.get_lane(keys[i])
            s, lat = lane.local_coordinates(position)
            if -0.5 <= s <= lane.length + 0.5 and abs(lat) <= lane.width_at(s) / 2 + margin:
                return True
        return False


class ActiveRoad(Road):
    """``Road`` that simulates only vehicles near the ego and prefilters pairwise searches.

    ``focus`` is the ego vehicle; vehicles farther than ``active_radius`` from it are
    frozen for the step. With ``active_radius`` = inf this is exactly highway-env's road.
    """

    def __init__(self, *args, active_radius: float = 150.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.active_radius = active_radius
        self.focus = None
        self._active: list = []
        self._positions = np.zeros((0, 2))
        self._candidates: list = []
        self.focus_hit = None  # what the focus vehicle first collided with

    def _refresh(self) -> None:
        """Recompute the active set and the position cache used by the searches."""
        vehicles = self.vehicles
        if self.focus is None or not np.isfinite(self.active_radius):
            self._active = list(vehicles)
        else:
            pos = np.array([v.position for v in vehicles]) if vehicles else np.zeros((0, 2))
            d = np.linalg.norm(pos - self.focus.position, axis=1)
            self._active = [v for v, di in zip(vehicles, d) if di <= self.active_radius]
        self._candidates = [o for o in self.vehicles + self.objects if not isinstance(o, Landmark)]
        self._positions = (
            np.array([o.position for o in self._candidates]) if self._candidates else np.zeros((0, 2))
        )

    def act(self) -> None:
        self._refresh()
        for vehicle in self._active:
            vehicle.act()

    def step(self, dt: float) -> None:
        active = self._active
        for vehicle in active:
            vehicle.step(dt)
        if not active:
            return
        pos = np.array([v.position for v in active])
        reach = max(v.diagonal for v in active) + 2.0 * max(abs(v.speed) for v in active) * dt + 1.0
        for i, vehicle in enumerate(active):
            d = np.linalg.norm(pos[i + 1:] - pos[i], axis=1)
            for j in np.flatnonzero(d < reach + 1.0):
                self._collide(vehicle, active[i + 1 + j], dt)
        if self.objects:
            obj_pos = np.array([o.position for o in self.objects])
            for i, vehicle in enumerate(active):
                d = np.linalg.norm(obj_pos - pos[i], axis=1)
                for j in np.flatnonzero(d < reach + 6.0):
                    self._collide(vehicle, self.objects[j], dt)

    def _collide(self, a, b, dt: float) -> None:
        """highway-env's collision handling, remembering what the focus vehicle hit first."""
        focus = self.focus
        if focus is None or self.focus_hit is not None or (a is not focus and b is not focus):
            a.handle_collisions(b, dt)
            return
        a.handle_collisions(b, dt)
        # A collision shows as `crashed` (overlap now) or `impact` (overlap within dt).
        if focus.crashed or focus.impact is not None:
            self.focus_hit = b if a is focus else a

    def neighbour_vehicles(self, vehicle, lane_index=None):
        """As highway-env's, over the vehicles and objects within ``NEIGHBOUR_RADIUS``."""
        if len(self._positions) != len(self._candidates) or not self._candidates:
            self._refresh()
        near = np.flatnonzero(np.linalg.norm(self._positions - vehicle.position, axis=1) < NEIGHBOUR_RADIUS)
        saved_v, saved_o = self.vehicles, self.objects
        self.vehicles = [self._candidates[i] for i in near]
        self.objects = []
        try:
            return super().neighbour_vehicles(vehicle, lane_index)
        finally:
            self.vehicles, self.objects = saved_v, saved_o
