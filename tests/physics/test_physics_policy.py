"""Behaviour tests of the physics policy (IDM + MOBIL + lane keeping) driving the real simulator.

The pure IDM/MOBIL maths is unit-tested in ``test_idm_mobil.py``; here ``IDMMobilPolicy``
drives ``DrivingEnv`` in hand-built situations: an empty straight three-lane road
(traffic, obstacles and side traffic switched off) on which the tests place the ego,
``TrafficCar`` s and ``BrokenDownCar`` s themselves. Lane slots: 0 = leftmost, the ego
starts in slot 1 (the middle lane). No mocks: every number comes from the simulator.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import step_mdp

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.envs.action import MAX_ACCELERATION
from pe_rlhf.envs.blocks import ROAD_SPEED, RouteBuilder
from pe_rlhf.envs.route import Route
from pe_rlhf.envs.scene import EGO_START, Scene, generate_scene
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.envs.traffic import BrokenDownCar, TrafficCar
from pe_rlhf.physics import IDMMobilPolicy, MOBILParams, PhysicsConfig
from pe_rlhf.physics.idm import idm_acceleration, idm_equilibrium_gap
from pe_rlhf.physics.module import PhysicsPolicyModule
from pe_rlhf.envs.perception import ego_lane_slot, neighbours

from _scenes import (CAR_LENGTH, DT, EMPTY_STRAIGHT, LONG_ROAD_SEED, add_car, add_obstacle,  # noqa: E402,F401
                     bumper_gap,
                     drive, lane_pose, long_road_env, long_road_scene, place_ego, progress_of, straight_env)


# --------------------------------------------------------------------------- 1. free road


@pytest.mark.parametrize(
    "lateral, dheading",
    [(0.0, 0.0), (1.2, 0.05), (-1.5, -0.1)],
    ids=["centred", "right-offset", "left-offset"],
)
def test_free_road_reaches_speed_limit_and_keeps_lane(lateral, dheading):
    env = straight_env(scene_seed=0)
    limit = env.road.network.get_lane(env.vehicle.lane_index).speed_limit
    assert limit == ROAD_SPEED == 15.0
    place_ego(env, EGO_START, lane=1, speed=8.0, lateral=lateral, dheading=dheading)
    policy = IDMMobilPolicy()
    policy.reset()
    speeds, offsets, slots = [], [], []

    def record(env, action, info):
        speeds.append(env.vehicle.speed)
        slot, offset = ego_lane_slot(env)
        slots.append(slot)
        offsets.append(offset)

    actions, info, terminated = drive(env, policy, 150, record)
    speeds, offsets = np.array(speeds), np.array(offsets)
    assert len(speeds) == 150 and not terminated, info
    # Speed rises monotonically towards the limit, never overshoots it, and settles within 1 m/s.
    assert np.all(np.diff(speeds) >= -1e-9)
    assert speeds.max() <= limit + 0.05
    assert np.all(np.abs(speeds[100:] - limit) < 1.0), speeds[100]  # from t = 10 s on
    assert abs(speeds[-1] - limit) < 0.1
    # Lane keeping: same lane throughout, converges without crossing to the other side.
    assert set(slots) == {1}
    assert np.all(np.abs(offsets[30:]) < 0.3), np.abs(offsets[30:]).max()  # from t = 3 s on
    assert np.all(np.abs(offsets[100:]) < 0.05)
    if lateral != 0.0:
        assert np.all(np.sign(offsets[np.abs(offsets) > 0.05]) == np.sign(lateral))  # no overshoot
    assert np.abs(actions[30:, 0]).max() < 0.1  # steering calms down once in lane
    assert not (info["crash_vehicle"] or info["crash_object"] or info["out_of_road"])


# --------------------------------------------------------------------------- 2. car following


@pytest.mark.parametrize("initial_gap", [30.0, 60.0])
def test_car_following_settles_at_idm_equilibrium(initial_gap):
    env = long_road_env()
    leader = add_car(env, env.progress + CAR_LENGTH + initial_gap, lane=1, speed=8.0, target_speed=8.0)
    config = PhysicsConfig(use_mobil=False)
    policy = IDMMobilPolicy(config)
    policy.reset()
    gaps, slots = [], []

    def record(env, action, info):
        gaps.append(bumper_gap(env, leader))
        slots.append(ego_lane_slot(env)[0])

    _, info, terminated = drive(env, policy, 400, record)  # 40 s
    assert len(gaps) == 400 and not terminated, info
    assert leader.speed == pytest.approx(8.0, abs=0.05)  # the scenario: a steady 8 m/s leader
    v0 = env.route.reference_lane(env.route.segments[env.route_segment]).speed_limit
    equilibrium = idm_equilibrium_gap(leader.speed, v0, config.idm)
    assert equilibrium == pytest.approx(22.95, abs=0.01)
    assert env.vehicle.speed == pytest.approx(leader.speed, abs=0.5)
    assert gaps[-1] == pytest.approx(equilibrium, rel=0.05)
    assert min(gaps) > 0.8 * equilibrium  # approaches without undershooting much, never collides
    assert not env.vehicle.crashed and not info["crash_vehicle"]
    assert set(slots) == {1}


# --------------------------------------------------------------------------- 3. emergency braking


@pytest.mark.parametrize(
    "gap, speed, saturates",
    [(35.0, 12.0, False), (25.0, 15.0, True)],
    ids=["35m-at-12mps", "25m-at-15mps"],
)
def test_brakes_to_a_stop_behind_a_stopped_vehicle(gap, speed, saturates):
    env = long_road_env()
    place_ego(env, 150.0, lane=1, speed=speed)
    stopped = add_car(env, env.progress + CAR_LENGTH + gap, lane=1, speed=0.0, target_speed=1e-3)
    policy = IDMMobilPolicy(PhysicsConfig(use_mobil=False))
    policy.reset()
    gaps = []
    actions, info, terminated = drive(env, policy, 150, lambda env, a, i: gaps.append(bumper_gap(env, stopped)))
    assert len(actions) == 150 and not terminated, info
    assert not env.vehicle.crashed and not info["crash_vehicle"]
    assert min(gaps) > 3.0, min(gaps)
    assert env.vehicle.speed < 0.05
    # Braking is bounded by IDM's max_braking (6 m/s^2 = throttle -1): the harder case uses all of it.
    assert actions[:, 1].min() >= -1.0
    if saturates:
        assert actions[:, 1].min() == pytest.approx(-1.0)
    else:
        assert actions[:, 1].min() > -1.0


# --------------------------------------------------------------------------- 4. MOBIL overtakes


def test_mobil_overtakes_a_slow_leader():
    env = long_road_env()
    leader = add_car(env, env.progress + CAR_LENGTH + 30.0, lane=1, speed=8.0, target_speed=8.0)
    policy = IDMMobilPolicy()
    policy.reset()
    decided_at, changed_at, slots = None, None, []

    def record(env, action, info):
        nonlocal decided_at, changed_at
        slot = ego_lane_slot(env)[0]
        slots.append(slot)
        if decided_at is None and policy.target_lane != 1:
            decided_at = env.time
        if changed_at is None and slot != 1:
            changed_at = env.time

    _, info, terminated = drive(env, policy, 250, record)
    assert not terminated, info
    assert decided_at is not None and decided_at <= 15.0
    assert changed_at is not None and changed_at <= 15.0
    assert slots[-1] in (0, 2) and slots[-1] == policy.target_lane
    assert abs(ego_lane_slot(env)[1]) < 0.3  # centred in the new lane
    assert info["overtakes"] >= 1
    assert env.progress > progress_of(env, leader) + CAR_LENGTH
    assert env.vehicle.speed > 14.0  # free again after the overtake
    assert not info["crash_vehicle"]


# --------------------------------------------------------------------------- 5. MOBIL safety


def _flank_scene(flank_lanes: tuple[int, ...], behind: float = 6.5):
    """Ego at 10 m/s behind an 8 m/s leader (an incentive to change lane), fast cars behind its flanks."""
    env = long_road_env()
    place_ego(env, 150.0, lane=1, speed=10.0)
    add_car(env, env.progress + CAR_LENGTH + 20.0, lane=1, speed=8.0, target_speed=8.0)
    for lane in flank_lanes:
        add_car(env, env.progress - behind, lane=lane, speed=14.0, target_speed=15.0)
    return env


def _target_lanes_over_one_second(env, policy) -> list[int]:
    lanes = []
    drive(env, policy, 11, lambda env, a, i: lanes.append(policy.target_lane))  # decisions at t = 0 and 1 s
    return lanes


@pytest.mark.parametrize("behind", [5.0, 6.5, 8.0])
def test_mobil_does_not_cut_in_front_of_fast_flank_vehicles(behind):
    env = _flank_scene((0, 2), behind)
    policy = IDMMobilPolicy()
    policy.reset()
    assert _target_lanes_over_one_second(env, policy) == [1] * 11
    assert ego_lane_slot(env)[0] == 1
    assert not env.vehicle.crashed


def test_mobil_flank_check_is_per_lane():
    # Control: without the flank cars the same situation makes the ego change lane at once ...
    env = _flank_scene(())
    policy = IDMMobilPolicy()
    policy.reset()
    assert _target_lanes_over_one_second(env, policy)[0] in (0, 2)
    # ... and with only the left flank taken it goes right.
    env = _flank_scene((0,))
    policy = IDMMobilPolicy()
    policy.reset()
    assert _target_lanes_over_one_second(env, policy)[0] == 2


# --------------------------------------------------------------------------- 6. politeness


def _politeness_scene():
    """A lane change left would slow the left-lane follower moderately (about -0.8 m/s^2, safe).

    Ego 8 m/s in slot 1 with an 8 m/s leader 30 m ahead; slot 2 equally slow (no gain there);
    slot 0 free ahead, with a 10 m/s car (target 15 m/s) 30 m behind the ego.
    """
    env = long_road_env()
    place_ego(env, 150.0, lane=1, speed=8.0)
    add_car(env, env.progress + CAR_LENGTH + 30.0, lane=1, speed=8.0, target_speed=8.0)
    add_car(env, env.progress + CAR_LENGTH + 30.0, lane=2, speed=8.0, target_speed=8.0)
    follower = add_car(env, env.progress - 30.0, lane=0, speed=10.0, target_speed=15.0)
    return env, follower


@pytest.mark.parametrize("politeness, expected", [(0.0, 0), (0.1, 0), (0.5, 1), (1.0, 1)])
def test_politeness_decides_the_constructed_lane_change(politeness, expected):
    env, _ = _politeness_scene()
    policy = IDMMobilPolicy(PhysicsConfig(mobil=MOBILParams(politeness=politeness)))
    policy.reset()
    items = neighbours(env, include_obstacles=False)
    assert policy._mobil(env, items, 1, policy.desired_speed(env)) == expected


def test_polite_driver_waits_for_the_follower_to_pass():
    def run(politeness):
        env, follower = _politeness_scene()
        policy = IDMMobilPolicy(PhysicsConfig(mobil=MOBILParams(politeness=politeness)))
        policy.reset()
        first, follower_ahead_at_first, follower_min_acc, slots = None, None, math.inf, [1]

        def record(env, action, info):
            nonlocal first, follower_ahead_at_first, follower_min_acc
            if first is None and policy.target_lane != 1:
                first = env.time - DT  # decided during the step just taken
                follower_ahead_at_first = progress_of(env, follower) > env.progress
            follower_min_acc = min(follower_min_acc, follower.action["acceleration"])
            slot = ego_lane_slot(env)[0]
            if slot != slots[-1]:
                slots.append(slot)

        _, info, _ = drive(env, policy, 200, record)
        assert not info["crash_vehicle"]
        return first, follower_ahead_at_first, follower_min_acc, slots

    rude_t, rude_ahead, rude_brake, rude_slots = run(0.0)
    polite_t, polite_ahead, polite_brake, polite_slots = run(1.0)
    # The impolite driver cuts in at once, making the follower brake moderately (not dangerously).
    assert rude_t == pytest.approx(0.0, abs=1e-9) and not rude_ahead
    assert -2.0 < rude_brake < -0.3
    # The polite one waits until the follower has passed, and nobody has to brake for it.
    assert polite_t is not None and polite_t > rude_t + 3.0
    assert polite_ahead
    assert polite_brake > -0.05
    assert rude_slots == polite_slots == [1, 0]  # one lane change each


# --------------------------------------------------------------------------- 7. obstacle blindness


@pytest.mark.parametrize("see_obstacles", [False, True])
def test_obstacles_are_the_blind_physics_policys_blind_spot(see_obstacles):
    env = straight_env(scene_seed=0)
    obstacle = add_obstacle(env, env.progress + 60.0, lane=1)
    s_obstacle = progress_of(env, obstacle)
    policy = IDMMobilPolicy(PhysicsConfig(see_obstacles=see_obstacles, stop_for_obstacles=False))
    policy.reset()
    actions, info, terminated = drive(env, policy, 150)  # 15 s
    if not see_obstacles:
        assert terminated and info["crash_object"] and not info["crash_vehicle"]
        assert len(actions) * DT < 15.0
        assert actions[:, 1].min() > 0.0  # never brakes for what it cannot see
    else:
        assert not info["crash_object"] and not info["crash_vehicle"] and not info["out_of_road"]
        assert len(actions) == 150
        assert env.progress > s_obstacle + CAR_LENGTH
        assert ego_lane_slot(env)[0] != 1


def test_stop_for_obstacles_brakes_behind_the_obstacle_and_never_passes_it():
    """The paper's IDM-MOBIL failure: IDM stops for a broken-down car, MOBIL does not pass it."""
    env = straight_env(scene_seed=0)
    obstacle = add_obstacle(env, env.progress + 60.0, lane=1)
    s_obstacle = progress_of(env, obstacle)
    assert PhysicsConfig().stop_for_obstacles  # the default: a safe fallback
    policy = IDMMobilPolicy(PhysicsConfig())
    policy.reset()
    actions, info, terminated = drive(env, policy, 200)  # 20 s
    assert not terminated and not info["crash_object"] and not info["crash_vehicle"]
    assert len(actions) == 200
    assert actions[:, 1].min() < -0.2  # it brakes for what IDM now sees
    gap = s_obstacle - env.progress - CAR_LENGTH
    assert 0.0 < gap < 15.0  # stopped behind it, about IDM's jam distance s0 = 10 m away
    assert env.vehicle.speed < 0.5
    assert ego_lane_slot(env)[0] == 1  # MOBIL still weighs vehicles only: no lane change to pass


# --------------------------------------------------------------------------- 8. ablation switches


def test_without_mobil_the_ego_never_changes_lane():
    env = long_road_env()
    add_car(env, env.progress + CAR_LENGTH + 30.0, lane=1, speed=8.0, target_speed=8.0)
    policy = IDMMobilPolicy(PhysicsConfig(use_mobil=False))
    policy.reset()
    targets, slots = set(), set()

    def record(env, action, info):
        targets.add(policy.target_lane)
        slots.add(ego_lane_slot(env)[0])

    _, info, terminated = drive(env, policy, 200, record)  # 20 s
    assert not terminated, info
    assert targets == {1} and slots == {1}
    assert env.vehicle.speed == pytest.approx(8.0, abs=0.5)  # stuck behind the leader instead


@pytest.mark.parametrize("use_mobil", [False, True])
def test_without_idm_the_ego_ignores_a_slow_leader(use_mobil):
    env = long_road_env()
    leader = add_car(env, env.progress + CAR_LENGTH + 30.0, lane=1, speed=8.0, target_speed=8.0)
    config = PhysicsConfig(use_idm=False, use_mobil=use_mobil)
    policy = IDMMobilPolicy(config)
    policy.reset()
    mismatches, steps, info, terminated = [], 0, {}, False
    while steps < 200 and not terminated:
        free_road = idm_acceleration(env.vehicle.speed, policy.desired_speed(env), params=config.idm)
        action = policy(env)
        mismatches.append(abs(action[1] - free_road / MAX_ACCELERATION))
        _, _, terminated, _, info = env.step(action)
        steps += 1
    assert max(mismatches) < 1e-6  # the throttle is the free-road IDM, whatever the leader does
    if not use_mobil:
        assert terminated and info["crash_vehicle"]
        assert bumper_gap(env, leader) < 1.0
    else:
        # MOBIL still sees the leader and steers around it: no crash, but no braking either.
        assert not info["crash_vehicle"] and ego_lane_slot(env)[0] != 1
        assert env.vehicle.speed > 14.9


# --------------------------------------------------------------------------- 9. the test split


def test_idm_mobil_on_test_seeds_is_sane():
    env = make_gym_env(DrivingConfig(split="test"))
    policy = IDMMobilPolicy()
    successes, failures = 0, []
    for seed in range(1000, 1004):  # 1002 times out behind an obstacle (1000 steps): a failure the test accepts
        env.reset(options={"scene_seed": seed})
        policy.reset()
        while True:
            action = policy(env)
            assert isinstance(action, np.ndarray) and action.shape == (2,) and action.dtype == np.float32
            assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0), (seed, action)
            _, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        if info["success"]:
            successes += 1
            assert not (info["crash_vehicle"] or info["crash_object"] or info["out_of_road"])
        else:
            reasons = [k for k in ("crash_vehicle", "crash_object", "out_of_road") if info[k]]
            assert reasons or truncated, (seed, info)
            failures.append((seed, reasons or ["timeout"]))
    assert successes >= 2, failures


# --------------------------------------------------------------------------- 10. TorchRL module


def reset_to_scene(torch_env, scene_seed: int):
    """Reset a ``make_env`` env to scene ``scene_seed``.

    Through the base env: ``TransformedEnv.reset`` keeps only the reset and state-spec
    keys of its input, and ``scene_seed`` is in neither, so ``make_env(...).reset(td)``
    currently drops the requested seed and draws a random scene.
    """
    td = torch_env.base_env.reset(TensorDict({"scene_seed": torch.tensor([scene_seed])}, batch_size=[]))
    assert unwrap(torch_env).scene_seed == scene_seed
    return td


def test_torchrl_module_matches_the_plain_policy():
    config = DrivingConfig(split="test")
    seed = 1001  # traffic and an early MOBIL lane change within the first 80 steps
    torch_env = make_env(config)
    module = PhysicsPolicyModule(torch_env)
    gym_env = make_gym_env(config)
    policy = IDMMobilPolicy()
    td = reset_to_scene(torch_env, seed)
    gym_env.reset(options={"scene_seed": seed})
    policy.reset()
    driving_env = unwrap(torch_env)
    assert driving_env.scene_seed == seed
    targets = set()
    for _ in range(80):
        td = module(td)
        action = policy(gym_env)
        targets.add(policy.target_lane)
        assert td["action"].shape == (2,) and td["action"].dtype == torch.float32
        np.testing.assert_allclose(td["action"].numpy(), action, atol=1e-6)
        assert module.policy.target_lane == policy.target_lane
        td = torch_env.step(td)
        gym_env.step(action)
        np.testing.assert_allclose(driving_env.vehicle.position, gym_env.vehicle.position, atol=1e-9)
        assert not td["next", "done"].item()
        td = step_mdp(td)
    assert len(targets) > 1  # the comparison covered a lane change, not only lane keeping


# --------------------------------------------------------------------------- regressions (bugs found and fixed)


class ParkedCar(TrafficCar):
    """A vehicle standing still at whatever pose it was given."""

    def act(self, action=None):
        self.action = {"steering": 0.0, "acceleration": 0.0}


def test_angled_vehicle_nosing_into_the_lane_is_seen():
    env = long_road_env()
    place_ego(env, 150.0, lane=1, speed=10.0)
    pos, heading = lane_pose(env, env.progress + 30.0, 1)
    lateral = np.array([-math.sin(heading), math.cos(heading)])
    # Centre 2.75 m right of the ego's lane centre (just outside occupies()' 2.65 m), turned
    # 0.6 rad towards the ego's lane: its front corner reaches 0.70 m from the lane centre,
    # inside the ego's body (half width 0.95 m).
    car = ParkedCar(env.road, pos + 2.75 * lateral, heading - 0.6, 0.0, target_speed=1e-3)
    env.road.vehicles.append(car)
    corners = [env.route.lateral_offset(c, env.route_segment) for c in car.polygon()[:4]]
    assert min(corners) == pytest.approx(0.70, abs=0.02)
    policy = IDMMobilPolicy()
    policy.reset()
    _, info, _ = drive(env, policy, 100)
    assert not info["crash_vehicle"]


def test_module_starts_each_episode_with_a_fresh_target_lane():
    torch_env = make_env(DrivingConfig(**EMPTY_STRAIGHT))
    driving_env = unwrap(torch_env)
    driving_env._scenes[LONG_ROAD_SEED] = long_road_scene(900.0)
    module = PhysicsPolicyModule(torch_env)
    # Episode 1: a slow leader makes MOBIL pick a lane change at t = 0, and an invisible
    # obstacle ends the episode (crash) 0.2 s later.
    td = reset_to_scene(torch_env, LONG_ROAD_SEED)
    place_ego(driving_env, 150.0, lane=1, speed=12.0)
    add_car(driving_env, driving_env.progress + 25.0, lane=1, speed=6.0, target_speed=6.0)
    add_obstacle(driving_env, driving_env.progress + CAR_LENGTH + 2.0, lane=1)
    for _ in range(20):
        td = step_mdp(torch_env.step(module(td)))
        if td["done"].item():
            break
    assert td["crash_object"].item() and driving_env.time < 1.0
    assert module.policy.target_lane != 1
    # Episode 2: an empty road; the ego should just keep its lane.
    td = reset_to_scene(torch_env, LONG_ROAD_SEED)
    steering = []
    for _ in range(20):
        td = module(td)
        steering.append(abs(float(td["action"][0])))
        td = step_mdp(torch_env.step(td))
    assert max(steering) < 0.05 and ego_lane_slot(driving_env)[0] == 1


def test_proposal_does_not_steer_into_an_occupied_lane_after_someone_else_drove():
    env = long_road_env()
    place_ego(env, 150.0, lane=1, speed=10.0)
    proposer = IDMMobilPolicy()  # queried every step, never applied (a physics proposal)
    proposer.reset()
    driver = IDMMobilPolicy(PhysicsConfig(use_mobil=False))  # stands in for the agent
    driver.reset()
    driver(env)
    driver.target_lane = 0  # the agent moves to the left lane
    for _ in range(60):
        proposer(env)
        env.step(driver(env))
    slot, offset = ego_lane_slot(env)
    assert slot == 0 and abs(offset) < 0.1
    add_car(env, env.progress, lane=1, speed=env.vehicle.speed, target_speed=env.vehicle.speed)  # alongside
    proposal = proposer(env)
    assert proposal[0] < 0.05  # must not steer right, into the car alongside


def test_scene_generator_can_chain_straight_blocks():
    config = DrivingConfig(**{**EMPTY_STRAIGHT, "min_blocks": 3, "max_blocks": 3})
    scene = generate_scene(0, config)
    assert scene.blocks == ["straight"] * 3
