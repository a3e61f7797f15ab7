"""Tests for the IDM + MOBIL physics policy maths."""

from __future__ import annotations

import math

import pytest

from pe_rlhf.physics import (
    IDMParams,
    LaneChangeAccelerations,
    MOBILParams,
    idm_acceleration,
    idm_desired_gap,
    idm_equilibrium_gap,
    mobil_choose_lane,
    mobil_incentive,
    mobil_safe,
    mobil_should_change,
)

P = IDMParams()
V0 = 30.0


# ---------------------------------------------------------------- IDM


def test_idm_defaults_match_paper():
    assert (P.max_acceleration, P.comfortable_braking, P.minimum_gap) == (2.0, 5.0, 10.0)
    assert (P.time_headway, P.exponent, P.max_braking) == (1.5, 4.0, 6.0)


def test_free_road():
    assert idm_acceleration(0.0, V0) == P.max_acceleration
    assert idm_acceleration(V0, V0) == 0.0
    assert idm_acceleration(V0 + 2.0, V0) < 0.0
    assert 0.0 < idm_acceleration(V0 / 2, V0) < P.max_acceleration


def test_desired_gap():
    assert idm_desired_gap(0.0, 0.0, P) == P.minimum_gap
    assert idm_desired_gap(0.0, 5.0, P) == P.minimum_gap
    assert idm_desired_gap(10.0, 0.0, P) == pytest.approx(10.0 + 15.0)
    gaps = [idm_desired_gap(15.0, dv, P) for dv in (0.0, 2.0, 5.0, 10.0)]
    assert all(a < b for a, b in zip(gaps, gaps[1:]))
    # Leader much faster: dynamic term negative, clamped so s* stays at s0.
    for v, dv in [(5.0, -20.0), (15.0, -30.0), (1.0, -100.0)]:
        assert idm_desired_gap(v, dv, P) >= P.minimum_gap
    assert idm_desired_gap(5.0, -100.0, P) == P.minimum_gap


@pytest.mark.parametrize("v", [0.0, 5.0, 12.0, 20.0, 27.0])
def test_equilibrium_gap_gives_zero_acceleration(v):
    s_e = idm_equilibrium_gap(v, V0, P)
    assert s_e >= P.minimum_gap
    a_eq = idm_acceleration(v, V0, gap=s_e, leader_speed=v, params=P)
    assert a_eq == pytest.approx(0.0, abs=1e-9)
    assert idm_acceleration(v, V0, gap=s_e * 1.05, leader_speed=v, params=P) > 0.0
    assert idm_acceleration(v, V0, gap=s_e * 0.95, leader_speed=v, params=P) < 0.0


def test_equilibrium_gap_infinite_at_or_above_desired_speed():
    assert idm_equilibrium_gap(V0, V0, P) == math.inf
    assert idm_equilibrium_gap(V0 + 1.0, V0, P) == math.inf


@pytest.mark.parametrize("v_lead,v_init,gap_init", [(20.0, 0.0, 50.0), (15.0, 25.0, 80.0)])
def test_car_following_converges(v_lead, v_init, gap_init):
    dt, steps = 0.1, 6000  # 600 s
    v, gap, min_gap = v_init, gap_init, gap_init
    for _ in range(steps):
        a = idm_acceleration(v, V0, gap=gap, leader_speed=v_lead, params=P)
        v = max(0.0, v + a * dt)
        gap += (v_lead - v) * dt
        min_gap = min(min_gap, gap)
    s_e = idm_equilibrium_gap(v_lead, V0, P)
    assert min_gap > 0.0
    assert v == pytest.approx(v_lead, rel=0.01)
    assert gap == pytest.approx(s_e, rel=0.01)


def test_emergency_braking_clipped():
    assert idm_acceleration(15.0, V0, gap=15.0, leader_speed=0.0, params=P) == -P.max_braking
    assert idm_acceleration(15.0, V0, gap=0.0, leader_speed=0.0, params=P) == -P.max_braking
    assert idm_acceleration(0.0, V0, gap=-1.0, leader_speed=5.0, params=P) == -P.max_braking
    # gap without leader speed is a stationary obstacle
    assert idm_acceleration(15.0, V0, gap=15.0, params=P) == -P.max_braking


def test_output_always_within_bounds():
    for v in (0.0, 5.0, 30.0, 45.0):
        for gap in (None, 0.5, 5.0, 50.0, 500.0):
            for vl in (0.0, 15.0, 40.0):
                a = idm_acceleration(v, V0, gap=gap, leader_speed=vl, params=P)
                assert -P.max_braking <= a <= P.max_acceleration


def test_stops_before_stationary_obstacle():
    dt, v, gap, min_gap = 0.1, 10.0, 60.0, 60.0
    for _ in range(3000):  # 300 s
        a = idm_acceleration(v, V0, gap=gap, leader_speed=0.0, params=P)
        v = max(0.0, v + a * dt)
        gap -= v * dt
        min_gap = min(min_gap, gap)
    assert min_gap > 0.0
    assert gap > 0.0
    assert v < 0.1
    assert gap > 0.5 * P.minimum_gap


def test_idm_validation():
    with pytest.raises(ValueError, match="comfortable_braking"):
        IDMParams(comfortable_braking=-5.0)
    with pytest.raises(ValueError, match="minimum_gap"):
        IDMParams(minimum_gap=0.0)
    with pytest.raises(ValueError, match="max_braking"):
        IDMParams(max_braking=float("nan"))
    with pytest.raises(ValueError, match="desired_speed"):
        idm_acceleration(10.0, 0.0)
    with pytest.raises(ValueError, match="desired_speed"):
        idm_equilibrium_gap(10.0, -1.0)


# ---------------------------------------------------------------- MOBIL

M = MOBILParams()


def test_mobil_defaults_match_paper():
    assert (M.politeness, M.threshold) == (0.1, 0.2)
    assert (M.max_safe_braking, M.lane_change_delay) == (2.0, 1.0)


def test_mobil_incentive_threshold():
    gain = LaneChangeAccelerations(ego_current=0.0, ego_target=1.0)
    assert mobil_incentive(gain, M) == 1.0
    assert mobil_should_change(gain, M)
    small = LaneChangeAccelerations(ego_current=0.5, ego_target=0.625)  # gain 0.125 < 0.2
    assert mobil_incentive(small, M) == 0.125
    assert not mobil_should_change(small, M)


def test_mobil_safety_veto():
    unsafe = LaneChangeAccelerations(
        ego_current=-4.0, ego_target=2.0, new_follower_before=0.0, new_follower_after=-3.0
    )
    assert mobil_incentive(unsafe, M) > 5.0
    assert not mobil_safe(unsafe, M)
    assert not mobil_should_change(unsafe, M)
    assert not mobil_should_change(unsafe, M, bias=100.0)
    ok = LaneChangeAccelerations(
        ego_current=-4.0, ego_target=2.0, new_follower_before=0.0, new_follower_after=-1.9
    )
    assert mobil_safe(ok, M)
    assert mobil_should_change(ok, M)
    assert mobil_safe(LaneChangeAccelerations(ego_current=0.0, ego_target=0.0), M)


def test_mobil_politeness():
    # Ego gains 0.5; new follower goes from 1.0 to -1.5 (loses 2.5, still safe).
    acc = LaneChangeAccelerations(
        ego_current=0.0, ego_target=0.5, new_follower_before=1.0, new_follower_after=-1.5
    )
    assert mobil_safe(acc, M)
    assert mobil_incentive(acc, M) == pytest.approx(0.25)  # 0.5 - 0.1 * 2.5
    assert mobil_should_change(acc, M)
    rude_averse = MOBILParams(politeness=0.2)
    assert mobil_incentive(acc, rude_averse) == pytest.approx(0.0)  # 0.5 - 0.2 * 2.5
    assert not mobil_should_change(acc, rude_averse)
    # Old follower's gain counts positively.
    acc2 = LaneChangeAccelerations(
        ego_current=0.0, ego_target=0.5, old_follower_before=-1.0, old_follower_after=1.0
    )
    assert mobil_incentive(acc2, M) == pytest.approx(0.7)


def test_mobil_bias():
    small = LaneChangeAccelerations(ego_current=0.0, ego_target=0.125)
    assert not mobil_should_change(small, M)
    assert mobil_should_change(small, M, bias=0.1)
    big = LaneChangeAccelerations(ego_current=0.0, ego_target=1.0)
    assert not mobil_should_change(big, M, bias=-1.0)


def test_mobil_choose_lane():
    left = LaneChangeAccelerations(ego_current=0.0, ego_target=0.5)
    right = LaneChangeAccelerations(ego_current=0.0, ego_target=1.0)
    weak = LaneChangeAccelerations(ego_current=0.0, ego_target=0.125)
    unsafe = LaneChangeAccelerations(
        ego_current=0.0, ego_target=3.0, new_follower_before=0.0, new_follower_after=-3.0
    )
    assert mobil_choose_lane(1, {0: left, 2: right}, M) == 2
    assert mobil_choose_lane(1, {0: left, 2: right}, M, biases={0: 1.0}) == 0
    assert mobil_choose_lane(1, {0: left, 2: right}, M, biases={2: -1.0}) == 0
    assert mobil_choose_lane(1, {0: weak, 2: unsafe}, M) == 1
    assert mobil_choose_lane(1, {}, M) == 1
    assert mobil_choose_lane(1, {0: weak, 2: unsafe}, M, biases={0: 0.5}) == 0


def test_mobil_validation():
    with pytest.raises(ValueError, match="politeness"):
        MOBILParams(politeness=1.5)
    with pytest.raises(ValueError, match="threshold"):
        MOBILParams(threshold=-0.1)
    with pytest.raises(ValueError, match="max_safe_braking"):
        MOBILParams(max_safe_braking=-2.0)
    with pytest.raises(ValueError, match="lane_change_delay"):
        MOBILParams(lane_change_delay=-1.0)
    with pytest.raises(ValueError, match="new_follower"):
        LaneChangeAccelerations(ego_current=0.0, ego_target=1.0, new_follower_before=0.0)
