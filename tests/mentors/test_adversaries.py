"""The persistent adversaries (``pe_rlhf.mentors.adversaries``) do what their names say on hand-built scenes of
the real simulator: each is driven alone (its action repeated every step) until the episode ends."""

from __future__ import annotations

import numpy as np
import pytest

from pe_rlhf.evaluation.policies import make_policy
from pe_rlhf.mentors import ADVERSARY_NAMES, make_mentor
from pe_rlhf.mentors.adversaries import nearest_road_user
from _scenes import add_car, add_obstacle, drive, long_road_env, place_ego, straight_env


def run_alone(env, mentor, steps: int = 200):
    mentor.reset(env)
    return drive(env, lambda e: mentor.decide(e, np.zeros(2, np.float32)).action, steps)


def test_every_adversary_is_registered_and_takes_over_at_every_step():
    env = straight_env()
    for name in ADVERSARY_NAMES:
        mentor = make_mentor(name, seed=0)
        mentor.reset(env)
        decisions = [mentor.decide(env, np.zeros(2, np.float32)) for _ in range(5)]
        assert all(d.takeover for d in decisions), name
        assert all(d.action.shape == (2,) and np.all(np.abs(d.action) <= 1) for d in decisions), name
        assert callable(make_policy(name, 0))  # an evaluation policy too
    with pytest.raises(ValueError, match="takes no overrides"):
        make_mentor("never-brake", action_noise=0.1)


def test_seek_collision_aims_at_the_car_in_the_next_lane_and_hits_it():
    env = long_road_env(400.0)
    place_ego(env, 60.0, lane=1, speed=10.0)
    car = add_car(env, 90.0, lane=2, speed=5.0, target_speed=5.0)
    mentor = make_mentor("seek-collision")
    assert nearest_road_user(env.unwrapped) is car
    first = mentor.act(env)
    assert first[1] == 1.0 and first[0] > 0.05  # full throttle, steering towards lane 2 (+lateral)
    actions, info, terminated = run_alone(env, mentor)
    assert terminated and info["crash_vehicle"]
    assert np.all(actions[:, 1] == 1.0)


def test_never_brake_runs_into_a_standing_obstacle_at_full_throttle():
    env = long_road_env(400.0)
    place_ego(env, 60.0, lane=1, speed=10.0)
    add_obstacle(env, 120.0, lane=1)
    actions, info, terminated = run_alone(env, make_mentor("never-brake"))
    assert terminated and info["crash_object"]
    assert np.all(actions[:, 1] == 1.0) and np.all(np.abs(actions[:, 0]) < 0.05)  # straight on, never braking


@pytest.mark.parametrize("lane, side", [(0, -1.0), (2, 1.0)])
def test_drift_off_road_leaves_the_road_on_the_nearer_side(lane, side):
    env = long_road_env(400.0)
    place_ego(env, 60.0, lane=lane, speed=10.0)
    actions, info, terminated = run_alone(env, make_mentor("drift-off-road"))
    assert terminated and info["out_of_road"] and not info["crash_vehicle"]
    assert np.all(np.sign(actions[:, 0]) == side) and np.all(actions[:, 1] == 0.0)


def test_uniform_random_is_seeded_and_covers_the_square():
    env = straight_env()
    a = np.array([make_mentor("uniform-random", seed=3).act(env) for _ in range(1)])
    m1, m2 = make_mentor("uniform-random", seed=3), make_mentor("uniform-random", seed=3)
    s1 = np.array([m1.act(env) for _ in range(400)])
    s2 = np.array([m2.act(env) for _ in range(400)])
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(a[0], s1[0])
    assert s1.min() >= -1 and s1.max() <= 1
    assert abs(s1.mean()) < 0.1 and s1.std() == pytest.approx(1 / np.sqrt(3), abs=0.05)
