"""Rule-based traffic: IDM/MOBIL cars and trucks (highway-env's models) that give way at junctions.

Background vehicles are highway-env ``IDMVehicle`` s that never collide with each
other (they do collide with the ego and with obstacles). They see vehicles *and*
static obstacles (highway-env's neighbour search includes road objects), so they
stop for and change lanes around broken-down cars. Side traffic arriving on a lane
tagged with a :class:`~pe_rlhf.envs.blocks.Junction` waits at the stop line until
the junction is free of other vehicles and no vehicle is about to arrive, then
claims it (one side vehicle at a time) and goes.
"""

from __future__ import annotations

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.objects import Obstacle

OBSTACLE_LOOKAHEAD = 60.0  # [m] traffic plans around obstacles this far ahead in its lane
STALL_ABORT = 3.0  # [s] a lane change stalled at a standstill this long is given up
GIVE_WAY_DISTANCE = 20.0  # [m] from the stop line at which side traffic checks the junction
ARRIVAL_HORIZON = 5.0  # [s] a vehicle arriving within this time blocks the junction
CLEAR_MARGIN = 8.0  # [m] around the junction radius that must be free


class TrafficCar(IDMVehicle):
    """An IDM/MOBIL car that gives way on lanes tagged with a junction."""

    LENGTH = 4.5
    WIDTH = 1.9
    DISTANCE_WANTED = 4.0 + LENGTH
    COMFORT_ACC_MAX = 2.5
    POLITENESS = 0.2

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.claimed = None  # the Junction this vehicle holds
        # Background vehicles do not collide with each other (the ego still collides with
        # them, and they with obstacles): a pile-up of rule-based cars would block the
        # route for reasons no driver could fix.
        self.check_collisions = False
        self._stopped_for = 0.0

    def act(self, action=None):
        super().act(action)
        if self.crashed:
            return
        self._release_junction()
        lane = self.road.network.get_lane(self.lane_index)
        junction = getattr(lane, "junction", None)
        if junction is None or self.claimed is junction:
            return
        to_stop = lane.length - lane.local_coordinates(self.position)[0]
        if to_stop > GIVE_WAY_DISTANCE:
            return
        if junction.occupant is None and self._junction_clear(junction):
            junction.occupant = self
            self.claimed = junction
            return
        self.action["acceleration"] = min(self.action["acceleration"], self._stop_acceleration(to_stop - 1.0))

    def step(self, dt: float) -> None:
        super().step(dt)
        if self.speed < 0.0:  # IDM braking may overshoot zero; real cars stop, they do not reverse
            self.speed = 0.0
        self._stopped_for = self._stopped_for + dt if self.speed < 0.5 else 0.0

    def change_lane_policy(self) -> None:
        """MOBIL, plus: leave a lane blocked by an obstacle ahead, and give up stalled changes.

        highway-env's MOBIL alone deadlocks behind obstacles: a car queued behind cones
        keeps a lane change pending into a lane that is stopped too, forever.
        """
        if self.lane_index != self.target_lane_index:
            if self._stopped_for > STALL_ABORT:
                self.target_lane_index = self.lane_index
            return super().change_lane_policy()
        if self._obstacle_ahead(self.lane_index):
            for lane_index in self.road.network.side_lanes(self.lane_index):
                lane = self.road.network.get_lane(lane_index)
                if lane.is_reachable_from(self.position) and not self._obstacle_ahead(lane_index) \
                        and self._gap_ok(lane_index):
                    self.target_lane_index = lane_index
                    return
            return  # wait for a gap
        super().change_lane_policy()

    def _obstacle_ahead(self, lane_index) -> bool:
        lane = self.road.network.get_lane(lane_index)
        s_self = lane.local_coordinates(self.position)[0]
        for o in self.road.objects:
            if np.abs(o.position - self.position).max() > OBSTACLE_LOOKAHEAD + 5:
                continue
            s, lat = lane.local_coordinates(o.position)
            if 0 < s - s_self < OBSTACLE_LOOKAHEAD and abs(lat) < lane.width_at(s) / 2 + o.WIDTH / 2 - 0.3:
                return True
        return False

    def _gap_ok(self, lane_index) -> bool:
        """Room in ``lane_index`` beside us and acceptable braking for its follower."""
        front, rear = self.road.neighbour_vehicles(self, lane_index)
        if front is not None and self.lane_distance_to(front) < (self.LENGTH + front.LENGTH) / 2 + 2.0:
            return False
        if rear is not None:
            if rear.lane_distance_to(self) < (self.LENGTH + rear.LENGTH) / 2 + 2.0:
                return False
            if self.acceleration(ego_vehicle=rear, front_vehicle=self) < -2 * self.LANE_CHANGE_MAX_BRAKING_IMPOSED:
                return False
        return True

    def _stop_acceleration(self, gap: float) -> float:
        """IDM deceleration towards a standing obstacle ``gap`` metres ahead."""
        if gap <= 0.5:
            return -self.speed / 0.2  # hold still at the line
        v, v0 = max(self.speed, 0.0), max(self.target_speed, 1.0)
        s_star = self.DISTANCE_WANTED / 2 + v * self.TIME_WANTED + v * v / (
            2 * np.sqrt(self.COMFORT_ACC_MAX * -self.COMFORT_ACC_MIN))
        acc = self.COMFORT_ACC_MAX * (1 - (v / v0) ** self.DELTA - (s_star / gap) ** 2)
        return float(np.clip(acc, -self.ACC_MAX, self.ACC_MAX))

    def _junction_clear(self, junction) -> bool:
        """No vehicle in or near the junction, none arriving within ``ARRIVAL_HORIZON``."""
        for other in self.road.vehicles:
            if other is self:
                continue
            lane = self.road.network.get_lane(other.lane_index) if other.lane_index else None
            if getattr(lane, "junction", None) is junction:
                continue  # another side vehicle queueing on an arm
            offset = other.position - junction.centre
            dist = float(np.linalg.norm(offset))
            if dist < junction.radius + CLEAR_MARGIN:
                return False
            closing = -float(np.dot(other.velocity, offset)) / dist
            if closing > 0.5 and (dist - junction.radius) / closing < ARRIVAL_HORIZON:
                return False
        return True

    def _release_junction(self) -> None:
        j = self.claimed
        if j is None:
            return
        lane = self.road.network.get_lane(self.lane_index)
        if getattr(lane, "junction", None) is None and np.linalg.norm(self.position - j.centre) > j.radius + 2.0:
            j.occupant = None
            self.claimed = None


class TrafficTruck(TrafficCar):
    """A longer, slower IDM/MOBIL vehicle."""

    LENGTH = 9.0
    WIDTH = 2.5
    DISTANCE_WANTED = 4.0 + LENGTH
    COMFORT_ACC_MAX = 1.5


class BrokenDownCar(Obstacle):
    """A stationary car blocking a lane."""

    LENGTH = 4.5
    WIDTH = 1.9
    color = (150, 95, 60)  # drawn brown, apart from the (yellow) ego


class TrafficCone(Obstacle):
    """A traffic cone (solid: touching it is a collision)."""

    LENGTH = 0.5
    WIDTH = 0.5
    color = (255, 130, 0)


class WarningTriangle(Obstacle):
    """A warning triangle set up behind a broken-down car."""

    LENGTH = 0.4
    WIDTH = 0.7
    color = (220, 30, 30)


def release_claims(vehicle) -> None:
    """Free a junction held by a vehicle that leaves the simulation."""
    j = getattr(vehicle, "claimed", None)
    if j is not None and j.occupant is vehicle:
        j.occupant = None
