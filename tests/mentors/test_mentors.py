"""Tests for the simulated mentors: skill profiles, the takeover rule, fatigue, determinism, state
round trips and the registry (real simulator, no mocks)."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest

from pe_rlhf.envs import make_gym_env, scene_seeds
from pe_rlhf.envs.traffic import BrokenDownCar
from pe_rlhf.evaluation import evaluate, make_policy
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.registry import MENTOR_NAMES, MentorPolicy, make_mentor
from pe_rlhf.mentors.simulated import PRESETS, SimulatedMentor, SkillProfile, preset
from pe_rlhf.mentors.takeover import TakeoverRule, chi2_quantile_2dof
from pe_rlhf.physics.policy import IDMMobilPolicy

# Scene 11 of the unsplit world starts with 187 m of straight road; no traffic, no obstacles.
EMPTY = {"split": None, "traffic_density": 0.0, "obstacle_density": 0.0, "side_traffic_probability": 0.0}
STRAIGHT_SCENE = 11


@pytest.fixture(scope="module")
def empty_env():
    env = make_gym_env(EMPTY)
    yield env
    env.close()


@pytest.fixture(scope="module")
def test_env():
    env = make_gym_env({"split": "test"})
    yield env
    env.close()


def _reset(env, mentor, seed):
    obs, _ = env.reset(options={"scene_seed": seed})
    mentor.reset(env)
    return obs


# -- profiles and names ------------------------------------------------------------------------
def test_presets_validate_and_alias():
    assert set(PRESETS) == {"professional", "amateur", "adversarial"}
    for profile in PRESETS.values():
        assert isinstance(profile, SkillProfile)
        assert SkillProfile(**dataclasses.asdict(profile)) == profile
    assert preset("bad") == PRESETS["adversarial"]
    pro, am, adv = PRESETS["professional"], PRESETS["amateur"], PRESETS["adversarial"]
    assert pro.error_rate == pro.fatigue_rate == pro.reaction_delay == pro.danger_seeking == 0
    assert am.action_noise > pro.action_noise and am.reaction_delay >= 2 and am.fatigue_rate > 0
    assert adv.error_rate > am.error_rate and adv.danger_seeking > 0 == am.danger_seeking


@pytest.mark.parametrize("field, value", [
    ("action_noise", -0.1), ("action_noise", math.nan), ("reaction_delay", 1.5), ("reaction_delay", -1),
    ("error_rate", 1.5), ("fatigue_rate", -1.0), ("max_fatigue", 0.5), ("danger_seeking", 2.0),
    ("speed_factor", 0.0), ("free_level", 1.0), ("min_span", 0), ("min_span", True),
])
def test_bad_profile_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        SkillProfile(**{field: value})


def test_unknown_names_and_fields_list_the_allowed_ones():
    with pytest.raises(ValueError, match="professional.*amateur|amateur.*professional") as e:
        make_mentor("expert")
    assert "adversarial" in str(e.value)
    with pytest.raises(ValueError, match="action_noise"):
        make_mentor("amateur", noise=0.1)
    with pytest.raises(ValueError, match="error_rate"):
        make_mentor("amateur", error_rate=-1)
    assert set(MENTOR_NAMES) >= {"professional", "amateur", "adversarial", "bad", "human"}
    assert make_mentor("bad").profile == PRESETS["adversarial"]
    assert make_mentor("amateur", action_noise=0.2).profile.action_noise == 0.2


def test_human_is_built_elsewhere():
    try:
        mentor = make_mentor("human")
    except ValueError as e:  # pygame missing: the message points at the module
        assert "pe_rlhf.mentors.human" in str(e)
    else:
        assert isinstance(mentor, Mentor) and mentor.name == "human"


def test_chi_square_threshold():
    assert chi2_quantile_2dof(0.95) == pytest.approx(5.991, abs=1e-3)
    rule = TakeoverRule(sigma=(0.15, 0.3), free_level=0.95)
    m = np.array([0.1, 0.2])
    assert not rule.unlikely(m + [0.15 * 2.4, 0.0], m)  # 2.4 sigma on one axis: d^2 = 5.76
    assert rule.unlikely(m + [0.15 * 2.5, 0.0], m)  # d^2 = 6.25
    assert rule.unlikely(m + [0.15 * 1.8, 0.3 * 1.8], m)  # d^2 = 6.48 over both axes
    with pytest.raises(ValueError, match="free_level"):
        TakeoverRule(free_level=1.0)


# -- takeover rule -----------------------------------------------------------------------------
def test_no_takeover_when_the_agent_drives_like_the_mentor(test_env):
    mentor = make_mentor("professional", seed=0)
    _reset(test_env, mentor, scene_seeds("test")[0])
    for _ in range(250):
        mentor.act(test_env)  # this step's plan; decide reuses it
        agent = mentor.last_intended.copy()
        decision = mentor.decide(test_env, agent)
        assert isinstance(decision, MentorDecision) and not decision.takeover, mentor.rule.last_reason
        _, _, terminated, truncated, _ = test_env.step(agent)
        assert not terminated or test_env.success
        if terminated or truncated:
            break
    assert mentor.controlled_steps == 0 and mentor.rule.takeovers == 0


def test_takeover_before_an_obstacle_avoids_the_crash(empty_env):
    def place_obstacle(env):
        lane = env.road.network.get_lane((*env.route.segments[1], 1))  # 50 m ahead, ego's lane
        position = lane.position(20.0, 0.0)
        env.road.objects.append(BrokenDownCar(env.road, position, lane.heading_at(20.0)))
        return env.route.project(position, 1)[1]  # its route progress [m]

    full_throttle = np.array([0.0, 1.0], dtype=np.float32)
    empty_env.reset(options={"scene_seed": STRAIGHT_SCENE})
    place_obstacle(empty_env)
    for _ in range(100):  # alone, the agent hits it
        *_, terminated, _, info = empty_env.step(full_throttle)
        if terminated:
            break
    assert info["crash_object"]

    mentor = make_mentor("professional", seed=0)
    _reset(empty_env, mentor, STRAIGHT_SCENE)
    obstacle_s = place_obstacle(empty_env)
    takeovers = []
    while empty_env.progress < obstacle_s + 10.0 and len(takeovers) < 150:
        decision = mentor.decide(empty_env, full_throttle)
        takeovers.append(decision.takeover)
        *_, terminated, _, info = empty_env.step(decision.action if decision.takeover else full_throttle)
        assert not info["crash_object"] and not info["out_of_road"]
        if terminated:
            break
    assert any(takeovers) and empty_env.progress > obstacle_s + 10.0


def test_minimum_span_after_one_bad_action(empty_env):
    mentor = make_mentor("professional", seed=0)
    _reset(empty_env, mentor, STRAIGHT_SCENE)
    flags = []
    for t in range(30):
        mentor.act(empty_env)
        agent = mentor.last_intended.copy()
        if t == 3:
            agent[0] = agent[0] + 0.8  # one wild steering input
        decision = mentor.decide(empty_env, agent)
        flags.append(decision.takeover)
        empty_env.step(decision.action if decision.takeover else agent)
    span = mentor.profile.min_span
    assert flags[:3] == [False] * 3
    assert flags[3:3 + span] == [True] * span  # held although the agent behaved from t = 4
    assert not any(flags[3 + span:])
    assert mentor.controlled_steps == span and mentor.rule.takeovers == 1


def test_road_departure_fires_the_danger_check(empty_env):
    mentor = make_mentor("professional", seed=0)
    _reset(empty_env, mentor, STRAIGHT_SCENE)
    empty_env.vehicle.speed = 20.0
    mentor.act(empty_env)
    intended = mentor.last_intended.copy()
    rule = mentor.rule
    assert rule.danger(empty_env, intended, intended) is None
    drift = intended + np.array([0.3, 0.0], dtype=np.float32)  # 2 sigma: likely, but leaves the road
    assert not rule.unlikely(drift, intended)
    assert rule.rollout(empty_env, drift)[0] == "off_road"
    decision = mentor.decide(empty_env, drift)
    assert decision.takeover and rule.last_reason == "off_road"

    mentor = make_mentor("professional", seed=0)
    _reset(empty_env, mentor, STRAIGHT_SCENE)
    assert mentor.decide(empty_env, np.array([1.0, 0.5])).takeover  # steering hard


# -- skill: fatigue, determinism, state --------------------------------------------------------
def _drive(env, mentor, steps, agent_fn, seeds, record):
    """Drive ``steps`` env steps across episodes; the mentor decides on ``agent_fn``'s action."""
    seeds = iter(seeds)
    obs = _reset(env, mentor, next(seeds))
    for _ in range(steps):
        agent = agent_fn(obs, env)
        decision = mentor.decide(env, agent)
        record(mentor, decision)
        obs, _, terminated, truncated, _ = env.step(decision.action if decision.takeover else agent)
        if terminated or truncated:
            obs = _reset(env, mentor, next(seeds))


def test_fatigue_degrades_the_amateur_with_controlled_steps(test_env):
    # x3 (the cap) after 200 controlled steps; HACO's tight belief, under which 0.8 of steering is overruled
    mentor = make_mentor("amateur", seed=3, fatigue_rate=10.0, steer_tolerance=0.15, throttle_tolerance=0.3)
    errors = []

    def bad_agent(obs, env):  # 0.8 of steering away from the mentor's plan: d^2 = 28, always overruled
        mentor.act(env)
        plan = mentor.last_intended
        return plan + np.array([-0.8 if plan[0] > 0 else 0.8, 0.0], dtype=np.float32)

    _drive(test_env, mentor, 360, bad_agent, scene_seeds("test"),
           lambda m, d: errors.append(float(np.abs(d.action - m.last_intended).mean())))
    assert mentor.controlled_steps == 360
    assert mentor.fatigue == mentor.profile.max_fatigue
    early, late = np.mean(errors[:60]), np.mean(errors[240:])
    assert late > 1.5 * early, (early, late)


def _physics_agent():
    policy = IDMMobilPolicy()
    return lambda obs, env: policy(env)


def test_same_seed_same_actions_different_seed_differs(test_env):
    a, b, c = (make_mentor("amateur", seed=s) for s in (7, 7, 8))
    agent = _physics_agent()
    obs = _reset(test_env, a, 1003)
    b.reset(test_env), c.reset(test_env)
    differs = False
    for _ in range(120):
        action = agent(obs, test_env)
        da, db, dc = (m.decide(test_env, action) for m in (a, b, c))
        assert da.takeover == db.takeover and np.array_equal(da.action, db.action)
        differs |= not np.array_equal(da.action, dc.action)
        obs, _, terminated, truncated, _ = test_env.step(da.action if da.takeover else action)
        if terminated or truncated:
            break
    assert differs and a.controlled_steps == b.controlled_steps


def test_state_dict_round_trip_mid_run(test_env):
    original = make_mentor("amateur", seed=5)
    agent = _physics_agent()
    obs = _reset(test_env, original, 1006)
    for t in range(60):
        action = agent(obs, test_env) + (np.array([1.8, 0.0]) if t == 55 else 0.0)  # mid-takeover at save
        d = original.decide(test_env, action)
        obs, *_ = test_env.step(d.action if d.takeover else action)
    state = copy.deepcopy(original.state_dict())
    assert state["rule"]["active"] and state["controlled_steps"] > 0
    restored = make_mentor("amateur", seed=123)
    restored.load_state_dict(state)
    for _ in range(80):
        action = agent(obs, test_env)
        d1, d2 = original.decide(test_env, action), restored.decide(test_env, action)
        assert d1.takeover == d2.takeover and np.array_equal(d1.action, d2.action)
        obs, _, terminated, truncated, _ = test_env.step(d1.action if d1.takeover else action)
        if terminated or truncated:
            break
    assert restored.state_dict()["rng"] == original.state_dict()["rng"]
    with pytest.raises(ValueError, match="profile"):
        make_mentor("professional").load_state_dict(state)


# -- registry ----------------------------------------------------------------------------------
def test_mentor_policy_evaluates_the_professional():
    policy = MentorPolicy(make_mentor("professional"))
    summary = evaluate(policy, scene_seeds("test")[:3], progress=False, name="professional")
    assert sum(e.success for e in summary.episodes) >= 2
    assert isinstance(make_policy("adversarial", 1), MentorPolicy)
    assert isinstance(make_policy("amateur", 1).mentor, SimulatedMentor)


# -- a mentor that steps in like a person ---------------------------------------------------------
def test_the_default_belief_tolerates_style_that_the_tight_one_overrules():
    agent, plan = np.array([0.5, 0.2]), np.array([0.0, 0.7])  # half a lane change early, slower
    assert TakeoverRule(sigma=(0.15, 0.3)).unlikely(agent, plan)
    assert not TakeoverRule().unlikely(agent, plan)
    assert TakeoverRule().unlikely(np.array([1.0, -1.0]), np.array([-0.5, 0.6]))  # a different manoeuvre


def test_a_stalled_car_is_taken_over_after_stall_steps(test_env):
    _reset(test_env, make_mentor("professional"), 1000)
    test_env.unwrapped.vehicle.speed = 0.0  # standing, as behind a broken-down vehicle
    agent, plan = np.array([0.0, 0.0]), np.array([0.0, 0.5])  # likely, harmless, but going nowhere
    rule = TakeoverRule(stall_steps=5)
    fired = [rule.step(test_env, agent, plan) for _ in range(7)]
    assert fired == [False] * 4 + [True] * 3 and rule.last_reason == "stall"
    off = TakeoverRule(stall_steps=0)
    assert not any(off.step(test_env, agent, plan) for _ in range(30))
    waiting = TakeoverRule(stall_steps=5)  # the mentor would stand still too: no stall
    assert not any(waiting.step(test_env, agent, np.array([0.0, 0.1])) for _ in range(30))


def test_the_stall_speed_is_a_mentor_setting(test_env):
    """SkillProfile.stall_speed reaches the rule: a car at 4 m/s going nowhere is taken over under a 6 m/s stall
    test (as under the default 5 m/s), never under 2 m/s."""
    assert make_mentor("professional").rule.stall_speed == 5.0
    agent, plan = np.array([0.0, 0.0]), np.array([0.0, 0.5])
    for stall_speed, taken in ((2.0, False), (6.0, True)):
        mentor = make_mentor("professional", stall_speed=stall_speed)
        _reset(test_env, mentor, 1000)
        test_env.unwrapped.vehicle.speed = 4.0
        assert any(mentor.rule.step(test_env, agent, plan) for _ in range(25)) == taken
    with pytest.raises(ValueError, match="stall_speed"):
        make_mentor("professional", stall_speed=-1.0)


def test_an_adversarial_seek_grabs_the_wheel(test_env):
    mentor = make_mentor("adversarial", seed=0, danger_seeking=1.0)
    _reset(test_env, mentor, 1000)
    mentor.act(test_env)
    decision = mentor.decide(test_env, mentor.last_intended.copy())  # the agent agrees with its plan
    assert decision.takeover
    calm = make_mentor("adversarial", seed=0, danger_seeking=1.0, seek_takes_over=False)
    _reset(test_env, calm, 1000)
    calm.act(test_env)
    assert not calm.decide(test_env, calm.last_intended.copy()).takeover


@pytest.mark.parametrize("adopt", [True, False])
def test_a_lane_change_the_mentor_did_not_plan_becomes_its_plan(test_env, adopt):
    from pe_rlhf.envs.geometry import LANE_WIDTH
    from pe_rlhf.mentors.driver import DriverParams, PrivilegedDriver
    from pe_rlhf.envs.perception import ego_lane_slot

    driver = PrivilegedDriver(DriverParams(adopt_lane=adopt))
    test_env.reset(options={"scene_seed": 1000})
    env = test_env.unwrapped
    driver(env)
    before, _ = ego_lane_slot(env)
    other = before + 1 if before + 1 < env.route.lanes else before - 1
    lane = env.road.network.get_lane((*env.route.segments[env.route_segment], before))
    s, _ = lane.local_coordinates(env.vehicle.position)
    env.vehicle.position = lane.position(s, (other - before) * LANE_WIDTH)  # the agent moved it one lane over
    assert ego_lane_slot(env)[0] == other
    driver(env)
    assert driver.target_lane == (other if adopt else before)


def test_manoeuvre_names_the_wrong_manoeuvre_under_way(empty_env):
    """``manoeuvre`` is None for a mentor that never errs, and the kind of error while one lasts (3-10 steps)."""
    careful = SimulatedMentor(preset("professional"), seed=0)
    erring = SimulatedMentor(dataclasses.replace(preset("amateur"), error_rate=1.0, fatigue_rate=0.0), seed=0)
    for mentor in (careful, erring):
        _reset(empty_env, mentor, STRAIGHT_SCENE)
    kinds = []
    for _ in range(12):
        careful.act(empty_env)
        erring.act(empty_env)
        kinds.append(erring.manoeuvre)
        assert careful.manoeuvre is None
        empty_env.step(erring.last_action)
    assert set(kinds) - {None} and set(kinds) <= {"steer", "brake", "throttle", None}
