"""The real-human mentor: keyboard/joystick input from posted pygame events, and the live window.

Headless (``SDL_VIDEODRIVER=dummy``), real pygame and a real ``DrivingEnv``; no mocks.
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402

from pe_rlhf.envs import make_gym_env  # noqa: E402
from pe_rlhf.mentors.base import Mentor  # noqa: E402
from pe_rlhf.mentors.human import PANEL_HEIGHT, SOURCE_COLORS, HumanMentor  # noqa: E402
from pe_rlhf.mentors.human_input import InputState, JoystickMapping  # noqa: E402
from _pygame_events import axis, key  # noqa: E402


@pytest.fixture
def state():
    pygame.display.init()
    pygame.display.set_mode((64, 64))
    pygame.event.clear()
    s = InputState()

    def step():
        s.pump()
        return s.poll()

    s.step = step
    yield s
    pygame.event.clear()


# -- keyboard ------------------------------------------------------------------------------
@pytest.mark.parametrize("up,down,left,right", [
    (pygame.K_UP, pygame.K_DOWN, pygame.K_LEFT, pygame.K_RIGHT),
    (pygame.K_w, pygame.K_s, pygame.K_a, pygame.K_d),
])
def test_keyboard_driving(state, up, down, left, right):
    takeover, action, paused, quit_ = state.step()
    assert not takeover and not paused and not quit_ and action.tolist() == [0.0, 0.0]
    key(up)
    takeover, action, *_ = state.step()
    assert takeover and action.dtype == np.float32 and action.shape == (2,) and action[1] > 0
    assert state.step().takeover  # still held
    key(up, down=False)
    assert not state.step().takeover
    key(down)
    takeover, action, *_ = state.step()
    assert takeover and action[1] < 0
    key(down, down=False)
    key(left)
    steer = [float(state.step().action[0]) for _ in range(12)]
    assert all(b < a for a, b in zip(steer[:9], steer[1:10])), steer  # ramps down by 0.1 ...
    assert steer[0] == pytest.approx(-0.1) and steer[9:] == [-1.0] * 3  # ... to full lock in 10
    key(left, down=False)
    takeover, action, *_ = state.step()
    assert not takeover and -1.0 < action[0] < 0.0  # released: returns towards 0
    key(right)
    assert state.step().action[0] == pytest.approx(0.1)  # counter-steer restarts from straight


def test_brake_wins_and_focus_loss_releases(state):
    key(pygame.K_UP)
    key(pygame.K_DOWN)
    assert state.step().action[1] == -1.0
    pygame.event.post(pygame.event.Event(pygame.WINDOWFOCUSLOST))
    assert not state.step().takeover


def test_pause_and_quit_keys(state):
    key(pygame.K_p)
    assert state.step().paused
    key(pygame.K_SPACE)
    assert not state.step().paused
    key(pygame.K_ESCAPE)
    assert state.step().quit
    s2 = InputState()
    pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_q))
    s2.pump()
    assert s2.poll().quit


# -- joystick ------------------------------------------------------------------------------
def test_joystick_axes_buttons_and_unplug(state):
    axis(0, 0.05)  # inside the 0.1 deadzone
    assert not state.step().takeover
    axis(0, 0.6)
    takeover, action, *_ = state.step()
    assert takeover and action[0] == pytest.approx((0.6 - 0.1) / 0.9)  # rescaled deadzone: 5/9
    axis(1, -1.0)  # stick pushed fully up: full throttle
    assert state.step().action[1] == pytest.approx(1.0)
    axis(1, 0.55)  # pulled back: brake
    assert state.step().action[1] == pytest.approx(-0.5)
    pygame.event.post(pygame.event.Event(pygame.JOYDEVICEREMOVED, instance_id=0))
    takeover, action, *_ = state.step()
    assert not takeover and action.tolist() == [0.0, 0.0]  # unplugged: control released
    pygame.event.post(pygame.event.Event(pygame.JOYBUTTONDOWN, instance_id=3, button=5))
    takeover, action, *_ = state.step()
    assert takeover and action.tolist() == [0.0, 0.0]  # a paddle alone takes over
    pygame.event.post(pygame.event.Event(pygame.JOYBUTTONUP, instance_id=3, button=5))
    assert not state.step().takeover


def test_pedal_mapping_and_quit_event():
    m = JoystickMapping(throttle_mode="pedals", takeover_buttons=(4,), pause_button=7)
    assert m.action({}) == (0.0, 0.0)  # pedals at rest (-1)
    assert m.action({5: 1.0}) == (0.0, 1.0)
    assert m.action({5: 1.0, 4: 1.0}) == (0.0, 0.0)
    with pytest.raises(ValueError):
        JoystickMapping(deadzone=1.0)
    pygame.display.init()
    pygame.display.set_mode((64, 64))
    pygame.event.clear()
    s = InputState(m)
    pygame.event.post(pygame.event.Event(pygame.JOYBUTTONDOWN, instance_id=0, button=2))
    pygame.event.post(pygame.event.Event(pygame.JOYBUTTONDOWN, instance_id=0, button=7))
    s.pump()
    takeover, _, paused, _ = s.poll()
    assert not takeover and paused  # button 2 is not a takeover button; 7 pauses
    pygame.event.post(pygame.event.Event(pygame.QUIT))
    s.pump()
    assert s.poll().quit


# -- the mentor with a real env ----------------------------------------------------------------
@pytest.fixture(scope="module")
def env():
    e = make_gym_env({"split": "test"})
    yield e
    e.close()


def test_human_mentor_drives_a_real_env(env, tmp_path):
    env.reset(options={"scene_seed": 1000})
    mentor = HumanMentor(fps=0)
    assert isinstance(mentor, Mentor)
    mentor.reset(env)
    pygame.event.clear()
    agent = np.array([0.2, 0.5], dtype=np.float32)
    script = {5: [(key, pygame.K_UP)], 8: [(key, pygame.K_LEFT)],
              12: [(key, pygame.K_LEFT, False), (key, pygame.K_UP, False)],
              15: [(axis, 0, 0.6)],
              18: [(lambda: pygame.event.post(pygame.event.Event(pygame.JOYDEVICEREMOVED, instance_id=0)),)]}
    takeovers = []
    for t in range(20):
        for fn, *args in script.get(t, []):
            fn(*args)
        d = mentor.decide(env, agent)
        takeovers.append(d.takeover)
        if t == 6:  # Up alone: the agent's steering stays (the handover), full throttle
            assert d.action.tolist() == pytest.approx([0.2, 1.0])
        if t in (9, 10):  # Left from t=8 ramps from the agent's 0.2
            assert d.action[0] == pytest.approx(0.2 - 0.1 * (t - 7), abs=1e-6) and d.action[1] == 1.0
        if t == 16:  # the stick steers; the untouched throttle axis keeps the agent's 0.5
            assert d.action[0] == pytest.approx(5 / 9) and d.action[1] == 0.5
        assert mentor.control == ("HUMAN" if d.takeover else "AGENT")
        env.step(d.action if d.takeover else agent)
    assert takeovers == [t in range(5, 12) or t in range(15, 18) for t in range(20)]
    assert mentor.takeover_count == 2 and mentor.takeover_steps == 10
    assert "takeovers: 2" in mentor.overlay_lines()
    assert not mentor.quit_requested

    frame = pygame.surfarray.array3d(mentor.screen)
    assert frame.shape[:2] == (900, 600)
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 10  # road, cars, panel, text
    badge = (20, 600 - PANEL_HEIGHT + 20)
    assert tuple(mentor.screen.get_at(badge))[:3] == SOURCE_COLORS["AGENT"]
    mentor.show_control("physics")  # the transform says who finally drove
    assert mentor.control == "PHYSICS" and tuple(mentor.screen.get_at(badge))[:3] == SOURCE_COLORS["PHYSICS"]
    with pytest.raises(ValueError):
        mentor.show_control("robot")

    path = mentor.screenshot(tmp_path / "w.png")
    img = pygame.image.load(str(path))
    assert img.get_size() == (900, 600)

    key(pygame.K_w)
    assert mentor.act(env)[1] == 1.0 and mentor.control == "HUMAN"  # driving alone ...
    assert mentor.takeover_count == 2  # ... is not a takeover of the agent
    key(pygame.K_w, down=False)
    state = mentor.state_dict()
    other = HumanMentor(fps=0)
    other.load_state_dict(state)
    assert other.state_dict() == state == {"takeover_count": 2, "takeover_steps": 10}

    pygame.event.post(pygame.event.Event(pygame.QUIT))  # closing the window
    d = mentor.decide(env, agent)
    assert mentor.quit_requested and not d.takeover


@pytest.mark.timeout(20)
def test_pause_blocks_until_unpaused(env):
    env.reset(options={"scene_seed": 1000})
    mentor = HumanMentor(fps=30)
    mentor.reset(env)
    pygame.event.clear()
    key(pygame.K_p)
    pygame.time.set_timer(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_SPACE), 400, loops=1)
    start = time.perf_counter()
    d = mentor.decide(env, np.zeros(2, dtype=np.float32))
    assert time.perf_counter() - start > 0.3  # held in the pause loop, clock ticking
    assert not mentor.paused and not d.takeover and mentor.steps == 1
    key(pygame.K_p)
    pygame.event.post(pygame.event.Event(pygame.QUIT))  # quitting ends a pause too
    mentor.decide(env, np.zeros(2, dtype=np.float32))
    assert mentor.quit_requested


def test_intervention_transform_tells_the_window_who_drives():
    """In PE-RLHF the human's takeover may execute physics' action; the window must say so."""
    from pe_rlhf.envs.torchrl_env import make_env
    from pe_rlhf.modules import QEnsemble
    from pe_rlhf.physics import IDMMobilPolicy
    from pe_rlhf.transforms import HybridActionSelector, InterventionTransform

    for epsilon, expected in ((-1e9, "HUMAN"), (1e9, "PHYSICS")):
        mentor = HumanMentor(fps=0)
        env = make_env({"split": "test"})
        selector = HybridActionSelector(QEnsemble(250, num_members=2, hidden=(8, 8)), epsilon_select=epsilon)
        env.append_transform(InterventionTransform(mentor, selector, IDMMobilPolicy()))
        td = env.reset(scene_seed=1000)
        key(pygame.K_UP)  # the person holds the accelerator: a takeover
        td["action"] = env.action_spec.zero()
        td = env.step(td)
        assert td["next", "intervention"].item()
        assert mentor.control == expected
        assert td["next", "mentor_selected"].item() == (expected == "HUMAN")
        key(pygame.K_UP, down=False)
        mentor.close()
        env.close()
