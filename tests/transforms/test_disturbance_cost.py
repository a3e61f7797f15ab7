"""Tests of ``TrafficDisturbanceCost`` (HAIM-DRL's traffic-disturbance cost) on built scenes.

The scene is the hand-built empty straight three-lane road of ``test_physics_policy`` (traffic,
obstacles and side traffic off) inside the TorchRL env; the tests place the ego and ``TrafficCar`` s
themselves and step the env with chosen throttles. Throttle -1 brakes at 6 m/s^2, -0.5 at 3 m/s^2
(:mod:`pe_rlhf.envs.action`); the default threshold is 5 m/s^2. No mocks: every number comes from the
simulator, except the mentor, which is scripted.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from _scenes import (
    EMPTY_STRAIGHT,
    LONG_ROAD_SEED,
    long_road_scene,
    add_car,
    place_ego,
)
from torchrl.envs.utils import check_env_specs, step_mdp

from pe_rlhf.envs import DrivingConfig
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.physics.idm import idm_equilibrium_gap
from pe_rlhf.transforms import InterventionTransform, TrafficDisturbanceCost
from pe_rlhf.transforms.disturbance import (
    PlatoonCar,
    disturbance_cost,
    predict_speed_loss,
)

EGO_S, SPEED = 100.0, 15.0  # [m] route progress and [m/s] speed of the ego (and its followers) at the start
HARD, GENTLE, COAST = -1.0, -0.5, 0.0  # throttles: 6 m/s^2, 3 m/s^2, none


class ScriptedMentor(Mentor):
    """Takes over while ``active``, braking hard."""

    def __init__(self):
        self.active = False

    def act(self, env) -> np.ndarray:
        return np.array([0.0, HARD], dtype=np.float32)

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        return MentorDecision(self.active, self.act(env))


def scene_env(mentor: Mentor | None = None, **kwargs):
    """``(torch env, its DrivingEnv, the transform, reset td)`` on the empty long road, ego at ``EGO_S``
    in the middle lane at ``SPEED``; with a mentor, an ``InterventionTransform`` comes first."""
    env = make_env(DrivingConfig(**EMPTY_STRAIGHT))
    sim = unwrap(env)
    sim._scenes[LONG_ROAD_SEED] = long_road_scene(900.0)
    if mentor is not None:
        env.append_transform(InterventionTransform(mentor))
    transform = TrafficDisturbanceCost(**kwargs)
    env.append_transform(transform)
    td = env.reset(TensorDict({"scene_seed": torch.tensor([LONG_ROAD_SEED])}, []))
    assert sim.scene_seed == LONG_ROAD_SEED and sim.road.vehicles == [sim.vehicle]
    place_ego(sim, EGO_S, lane=1, speed=SPEED)
    return env, sim, transform, td


def drive(env, td, throttles: list[float]) -> tuple[list[float], TensorDict]:
    """Step with each throttle (straight); returns the disturbance cost of each step and the last td."""
    costs = []
    for throttle in throttles:
        td["action"] = torch.tensor([0.0, throttle])
        td = env.step(td)
        costs.append(td["next", "disturbance_cost"].item())
        assert not td["next", "done"].item()
        td = step_mdp(td)
    return costs, td


# --------------------------------------------------------------------------- the env transform


def test_hard_brake_with_a_close_follower_is_charged_at_the_events_first_step_only():
    env, sim, transform, td = scene_env()
    add_car(sim, EGO_S - 20.0, lane=1, speed=SPEED, target_speed=SPEED)  # 15.5 m bumper gap
    costs, td = drive(env, td, [HARD, HARD, HARD])
    assert transform.last_deceleration == pytest.approx(6.0)  # measured from the simulator's speeds
    assert 0.0 < costs[0] < 1.0
    assert costs[1:] == [0.0, 0.0]  # the same braking event: charged once
    costs, td = drive(env, td, [COAST, HARD])  # the event ended; a new one starts
    assert costs[0] == 0.0 and costs[1] > 0.0


def test_the_cost_grows_with_the_followers_predicted_slowdown():
    def first_cost(gap: float) -> float:
        env, sim, _, td = scene_env()
        add_car(sim, EGO_S - gap, lane=1, speed=SPEED, target_speed=SPEED)
        return drive(env, td, [HARD])[0][0]

    near, mid, far = first_cost(12.0), first_cost(30.0), first_cost(55.0)
    assert near > mid > far > 0.0


@pytest.mark.parametrize("where", ["empty road", "car ahead", "car behind in the next lane", "car out of range"])
def test_no_follower_means_no_cost(where):
    env, sim, _, td = scene_env(follower_range=40.0)
    if where == "car ahead":
        add_car(sim, EGO_S + 20.0, lane=1, speed=SPEED, target_speed=SPEED)
    elif where == "car behind in the next lane":
        add_car(sim, EGO_S - 15.0, lane=2, speed=SPEED, target_speed=SPEED)
    elif where == "car out of range":
        add_car(sim, EGO_S - 45.0, lane=1, speed=SPEED, target_speed=SPEED)
    costs, _ = drive(env, td, [HARD, HARD])
    assert costs == [0.0, 0.0]


def test_braking_during_a_takeover_is_not_charged():
    mentor = ScriptedMentor()
    env, sim, transform, td = scene_env(mentor)
    add_car(sim, EGO_S - 20.0, lane=1, speed=SPEED, target_speed=SPEED)
    mentor.active = True  # the mentor brakes hard, whatever the agent proposes
    costs, td = drive(env, td, [COAST, COAST])
    assert transform.last_deceleration == pytest.approx(6.0)
    assert costs == [0.0, 0.0]
    mentor.active = False  # the agent keeps braking: the event began in the takeover, nothing is charged
    costs, td = drive(env, td, [HARD])
    assert costs == [0.0]
    costs, td = drive(env, td, [COAST, HARD])  # the agent's own braking event
    assert costs[0] == 0.0 and costs[1] > 0.0


def test_gentle_braking_is_not_charged_unless_below_the_threshold():
    env, sim, transform, td = scene_env()
    add_car(sim, EGO_S - 20.0, lane=1, speed=SPEED, target_speed=SPEED)
    costs, _ = drive(env, td, [GENTLE, GENTLE])
    assert transform.last_deceleration == pytest.approx(3.0)
    assert costs == [0.0, 0.0]
    env, sim, _, td = scene_env(threshold=2.5)
    add_car(sim, EGO_S - 20.0, lane=1, speed=SPEED, target_speed=SPEED)
    costs, _ = drive(env, td, [GENTLE, GENTLE])
    assert costs[0] > 0.0 and costs[1] == 0.0


def test_specs_reset_and_rollout_keys():
    env, _, _, _ = scene_env(ScriptedMentor())
    check_env_specs(env)
    td = env.reset(TensorDict({"scene_seed": torch.tensor([LONG_ROAD_SEED])}, []))
    assert td["disturbance_cost"].shape == (1,) and td["disturbance_cost"].item() == 0.0
    rollout = env.rollout(5, break_when_any_done=False)
    assert rollout["next", "disturbance_cost"].shape == (5, 1)
    assert rollout["next", "disturbance_cost"].dtype == torch.float32


@pytest.mark.parametrize("kwargs, field", [({"threshold": 0.0}, "threshold"), ({"horizon": -1.0}, "horizon"),
                                           ({"follower_range": math.inf}, "follower_range")])
def test_invalid_arguments_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        TrafficDisturbanceCost(**kwargs)


# --------------------------------------------------------------------------- the prediction


def test_no_loss_without_braking_at_the_idm_equilibrium():
    desired = 20.0
    gap = idm_equilibrium_gap(SPEED, desired)
    follower = PlatoonCar(s=-(gap + 4.5), speed=SPEED, desired_speed=desired, length=4.5)
    assert predict_speed_loss(0.0, SPEED, 4.5, 0.0, [follower], horizon=3.0)[0] == pytest.approx(0.0, abs=1e-6)


def test_loss_grows_with_the_deceleration_and_the_platoon_passes_it_on():
    followers = [PlatoonCar(-20.0, SPEED, SPEED, 4.5), PlatoonCar(-40.0, SPEED, SPEED, 4.5)]
    soft = predict_speed_loss(0.0, SPEED, 4.5, 2.0, followers, horizon=3.0)
    hard = predict_speed_loss(0.0, SPEED, 4.5, 6.0, followers, horizon=3.0)
    assert all(h > s for h, s in zip(hard, soft))
    assert hard[0] > 0.0 and hard[1] > 0.0  # the second follower slows down behind the first
    far = predict_speed_loss(0.0, SPEED, 4.5, 6.0, [PlatoonCar(-300.0, SPEED, SPEED, 4.5)], horizon=3.0)
    assert far[0] < 0.05 * hard[0]  # IDM still eases off a little for a stopping car 300 m ahead


def test_cost_is_one_minus_exp_of_the_mean_loss():
    assert disturbance_cost([]) == 0.0
    assert disturbance_cost([1.0, 3.0]) == pytest.approx(1 - math.exp(-2.0))
    assert disturbance_cost([0.0]) == 0.0
