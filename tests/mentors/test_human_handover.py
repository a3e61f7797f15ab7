"""The human takeover starts from the agent's action (the handover), from scripted pygame key events.

Holding only Up in a curve used to snap the wheel straight (the keyboard started from the person's own
steering, 0 after a reset). Headless (``SDL_VIDEODRIVER=dummy``), real pygame, a real ``DrivingEnv``.
"""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from pe_rlhf.mentors.human import HumanMentor  # noqa: E402
from pe_rlhf.mentors.human_input import InputState  # noqa: E402
from _pygame_events import axis, key  # noqa: E402

STEER_RATE = 0.1  # InputState's default key increment per poll
AGENT = np.array([0.4, 0.3], dtype=np.float32)  # the agent steers right (a curve), light throttle


@pytest.fixture
def drive():
    """``drive(script, agent, steps)``: the polled actions, ``script`` = {poll index: [event posters]}."""
    pygame.display.init()
    pygame.display.set_mode((64, 64))
    pygame.event.clear()
    state = InputState()

    def run(script, agent=AGENT, steps=8):
        polls = []
        for t in range(steps):
            for post in script.get(t, []):
                post()
            state.pump()
            polls.append(state.poll(agent))
        return polls

    run.state = state
    yield run
    pygame.event.clear()


def steering(polls):
    return [round(float(p.action[0]), 6) for p in polls]


def test_up_alone_keeps_the_agents_steering(drive):
    polls = drive({1: [lambda: key(pygame.K_UP)]}, steps=6)
    assert [p.takeover for p in polls] == [False] + [True] * 5
    assert abs(polls[1].action[0] - AGENT[0]) <= STEER_RATE  # the first human step: no snap to straight ...
    assert steering(polls[1:]) == [0.4] * 5  # ... and the untouched wheel stays where the agent had it
    assert [float(p.action[1]) for p in polls[1:]] == [1.0] * 5  # Up: full throttle


@pytest.mark.parametrize("steer_key, direction", [(pygame.K_RIGHT, 1), (pygame.K_LEFT, -1)])
def test_steering_keys_ramp_from_the_agents_steering(drive, steer_key, direction):
    polls = drive({0: [lambda: key(steer_key)]}, steps=7)
    s = steering(polls)
    assert abs(s[0] - AGENT[0]) <= STEER_RATE + 1e-6
    assert s == pytest.approx([min(1.0, 0.4 + direction * STEER_RATE * (t + 1)) for t in range(7)])
    # Left passes through straight (0.4, 0.3, ... -0.3): no restart from 0 when turning back from the agent's
    assert all(float(p.action[1]) == pytest.approx(AGENT[1]) for p in polls)  # throttle untouched: the agent's


def test_once_touched_the_person_drives_as_before(drive):
    """After the handover the ramps are the person's own: released, steering returns towards 0; a reversal of
    their own steering restarts from straight; released Up coasts."""
    polls = drive({0: [lambda: key(pygame.K_UP), lambda: key(pygame.K_RIGHT)], 2: [lambda: key(pygame.K_RIGHT, False)],
                   4: [lambda: key(pygame.K_LEFT)], 5: [lambda: key(pygame.K_UP, False)]}, steps=6)
    assert steering(polls) == pytest.approx([0.5, 0.6, 0.4, 0.2, -0.1, -0.2])
    assert [float(p.action[1]) for p in polls] == [1.0, 1.0, 1.0, 1.0, 1.0, 0.0]


def test_each_takeover_hands_over_from_the_agents_action_then(drive):
    first = drive({0: [lambda: key(pygame.K_UP)], 2: [lambda: key(pygame.K_UP, False)]}, steps=3)
    assert [p.takeover for p in first] == [True, True, False]
    second = drive({0: [lambda: key(pygame.K_DOWN)]}, agent=np.array([-0.7, 0.8], np.float32), steps=2)
    assert steering(second) == [-0.7, -0.7] and [float(p.action[1]) for p in second] == [-1.0, -1.0]  # brake at once


def test_without_an_agent_action_input_starts_from_the_persons_own(drive):
    """``poll()`` alone (driving alone, ``HumanMentor.act``): no handover, Up alone drives straight."""
    polls = drive({0: [lambda: key(pygame.K_UP)]}, agent=None, steps=2)
    assert steering(polls) == [0.0, 0.0]
    nan = drive({0: [lambda: key(pygame.K_UP, False)], 1: [lambda: key(pygame.K_UP)]},
                agent=np.array([np.nan, 0.3], np.float32), steps=2)
    assert steering(nan)[1] == 0.0  # a non-finite proposal is nothing to start from


def test_reset_makes_a_held_key_a_new_handover(drive):
    drive({0: [lambda: key(pygame.K_RIGHT)]}, steps=3)  # the person steers 0.7 and keeps holding Right
    drive.state.reset()
    polls = drive({}, agent=np.array([-0.2, 0.0], np.float32), steps=2)
    assert steering(polls) == pytest.approx([-0.1, 0.0])  # from the new episode's agent, not from 0.7


def test_joystick_untouched_axes_keep_the_agents_values(drive):
    """A paddle alone (stick at rest) keeps the agent's action; a moved stick commands its position."""
    button = pygame.event.Event(pygame.JOYBUTTONDOWN, instance_id=3, button=5)
    polls = drive({0: [lambda: pygame.event.post(button)], 2: [lambda: axis(0, -0.55, iid=3)]}, steps=3)
    assert [p.action.tolist() for p in polls[:2]] == [pytest.approx(AGENT.tolist())] * 2
    assert polls[2].action.tolist() == pytest.approx([-0.5, float(AGENT[1])])  # steered; throttle still untouched


@pytest.fixture(scope="module")
def haco_env():
    from pe_rlhf.envs.torchrl_env import make_env
    from pe_rlhf.transforms import InterventionTransform

    mentor = HumanMentor(fps=0)
    env = make_env({"split": "test"})
    env.append_transform(InterventionTransform(mentor))  # HACO: the mentor's action is executed
    yield env
    mentor.close()
    env.close()


def test_executed_steering_at_a_takeover_starts_from_the_agents(haco_env):
    """Through ``InterventionTransform`` (which hands ``HumanMentor.decide`` the agent's proposal): the agent
    steers 0.4; the person presses Up, then Left. The executed steering starts within one key increment
    of 0.4, holds while only Up is held, then ramps by one increment per step."""
    td = haco_env.reset(scene_seed=1000)
    pygame.event.clear()
    script = {2: [lambda: key(pygame.K_UP)], 4: [lambda: key(pygame.K_LEFT)]}
    executed, takeover = [], []
    for t in range(8):
        for post in script.get(t, []):
            post()
        td["action"] = torch.as_tensor(AGENT)
        td = haco_env.step(td)
        executed.append(td["next", "behavior_action"].tolist())
        takeover.append(bool(td["next", "intervention"].item()))
        td = td["next"]
    assert takeover == [False, False] + [True] * 6
    steer = [round(a[0], 6) for a in executed]
    assert steer[:2] == [0.4, 0.4]  # the agent drives
    assert abs(steer[2] - 0.4) <= STEER_RATE  # the first human step
    assert steer[2:] == pytest.approx([0.4, 0.4, 0.3, 0.2, 0.1, 0.0])  # holds under Up, then ramps with Left
    assert [a[1] for a in executed[2:]] == [1.0] * 6

