"""Road users ahead in the physics forecast (``pe_rlhf.physics.road_users``): a lane-following car is forecast along
its lanes with its own controller, where the real simulator moves it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pe_rlhf.physics.road_users import RoadUsers
from _scenes import add_car, curve_env, place_ego

BRAKE = np.array([0.0, -1.0], np.float32)
STEPS = 30  # policy steps of 0.1 s: the forecast's 3 s horizon
POSITION_TOLERANCE = 0.1  # [m] measured: at most 0.035 m over the 3 s (the controller at 0.1 s, interpolated)
HEADING_TOLERANCE = 0.02  # [rad] measured: at most 0.01 rad


@pytest.mark.parametrize("lane", [0, 2])  # the outer and the inner lane of the bend
def test_a_car_driving_into_a_bend_is_forecast_where_the_simulator_moves_it(lane):
    """A car 10 m before a 90-degree bend of radius 30 m, at its target speed (the IDM keeps it: the forecast keeps
    speeds), is forecast along its lane into the bend: within centimetres of the simulator's own trajectory at every
    step of the 3 s, where a straight line at its velocity is metres off (the model before)."""
    env = curve_env()
    place_ego(env, 2.0, lane=1, speed=0.0)  # standing far behind: the car drives on unhindered
    car = add_car(env, 30.0, lane, speed=8.0, target_speed=8.0)
    start, velocity, heading = car.position.copy(), car.velocity.copy(), car.heading
    forecast = RoadUsers([car], dt=0.1, steps=STEPS, substeps=2)  # the env's 20 Hz simulation: 2 sub-steps a step
    position_error, heading_error, straight_error = [], [], []
    for i in range(1, STEPS + 1):
        env.step(BRAKE)
        position_error.append(float(np.linalg.norm(forecast.positions[2 * i, 0] - car.position)))
        heading_error.append(abs(float(forecast.headings[2 * i, 0]) - car.heading))
        straight_error.append(float(np.linalg.norm(start + velocity * 0.1 * i - car.position)))
    assert car.speed == pytest.approx(8.0, abs=0.05) and abs(car.heading - heading) > 0.3  # into the bend
    assert max(position_error) < POSITION_TOLERANCE
    assert max(heading_error) < HEADING_TOLERANCE
    assert straight_error[-1] > 2.5


def test_a_static_object_stays_and_a_plain_vehicle_keeps_its_velocity():
    """Anything that does not follow lanes (an obstacle, a vehicle without a lane controller) moves in a straight
    line at its velocity: the model of every road user before."""
    from highway_env.vehicle.kinematics import Vehicle

    env = curve_env()
    mover = Vehicle(env.road, np.array([10.0, 2.0]), heading=0.3, speed=5.0)
    forecast = RoadUsers([mover], dt=0.1, steps=STEPS, substeps=2)
    expected = np.array([10.0, 2.0]) + 5.0 * 3.0 * np.array([math.cos(0.3), math.sin(0.3)])
    assert forecast.positions[-1, 0] == pytest.approx(expected)
    assert forecast.headings[-1, 0] == pytest.approx(0.3)


def test_lanes_or_velocity_forecasts_a_lane_follower_both_ways():
    """``model="lanes_or_velocity"``: a lane-following car is two paths, along its lanes and straight on at its
    velocity (a contact with either is a contact); an obstacle is one. ``"velocity"`` is the straight line alone."""
    from pe_rlhf.envs.traffic import BrokenDownCar

    env = curve_env()
    car = add_car(env, 30.0, 2, speed=8.0, target_speed=8.0)
    cone = BrokenDownCar(env.road, np.array([60.0, 0.0]), 0.0)
    lanes = RoadUsers([car, cone], dt=0.1, steps=STEPS, substeps=2, model="lanes")
    both = RoadUsers([car, cone], dt=0.1, steps=STEPS, substeps=2, model="lanes_or_velocity")
    straight = RoadUsers([car, cone], dt=0.1, steps=STEPS, substeps=2, model="velocity")
    assert (lanes.count, both.count, straight.count) == (2, 3, 2)
    assert both.positions[:, :2] == pytest.approx(lanes.positions)
    assert both.positions[:, 2] == pytest.approx(straight.positions[:, 0])
    assert np.linalg.norm(lanes.positions[-1, 0] - straight.positions[-1, 0]) > 2.5  # the bend: two places
    assert straight.positions[-1, 1] == pytest.approx([60.0, 0.0])
    with pytest.raises(ValueError, match="model='swerve'"):
        RoadUsers([car], dt=0.1, steps=STEPS, substeps=2, model="swerve")
