"""The person's window is closed or the gamepad unplugged mid-run: control returns to the agent (or the
run pauses: ``HumanMentor(on_disconnect="pause")``, ``mentor.kwargs.on_disconnect=pause``), and the
trainer checkpoints what was collected. Headless pygame, events posted as a person's would be."""

from __future__ import annotations

import csv
import time

import numpy as np
import pygame
import pytest
from _runs import UNIFORM_REPLAY, train

from pe_rlhf.envs import make_gym_env
from pe_rlhf.mentors.human import HumanMentor
from pe_rlhf.runtime.checkpoint import load_checkpoint
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config

pytestmark = pytest.mark.usefixtures("one_thread")
AGENT = np.array([0.1, 0.3], dtype=np.float32)


def post(kind, **attrs):
    pygame.event.post(pygame.event.Event(kind, **attrs))


def post_later(ms: int, kind, **attrs):
    pygame.time.set_timer(pygame.event.Event(kind, **attrs), ms, loops=1)


@pytest.fixture(scope="module")
def env():
    e = make_gym_env({"split": "test"})
    e.reset(options={"scene_seed": 1000})
    yield e
    e.close()


def mentor_for(env, on_disconnect: str) -> HumanMentor:
    mentor = HumanMentor(fps=30, on_disconnect=on_disconnect)
    mentor.reset(env)
    pygame.event.clear()
    return mentor


def test_window_closed_hands_control_to_the_agent_for_good(env):
    mentor = mentor_for(env, "agent")
    post(pygame.KEYDOWN, key=pygame.K_UP)
    assert mentor.decide(env, AGENT).takeover
    post(pygame.WINDOWCLOSE)
    post(pygame.QUIT)  # SDL sends both for one click: one disconnect
    d = mentor.decide(env, AGENT)
    assert not d.takeover and mentor.quit_requested and mentor.disconnects == 1
    assert mentor.screen is None and pygame.display.get_surface() is None  # the window is gone
    assert not mentor.decide(env, AGENT).takeover and mentor.control == "AGENT"  # and stays gone


@pytest.mark.timeout(30)
def test_pause_mode_reopens_a_closed_window_paused_until_the_person_is_back(env, monkeypatch):
    mentor = mentor_for(env, "pause")
    reopen = mentor._ensure_window

    def ensure_window():  # the person sees the window come back and presses P 0.4 s later
        closed = mentor.screen is None
        reopen()
        if closed:
            post_later(400, pygame.KEYDOWN, key=pygame.K_p)

    monkeypatch.setattr(mentor, "_ensure_window", ensure_window)
    post(pygame.QUIT)
    start = time.perf_counter()
    d = mentor.decide(env, AGENT)
    assert time.perf_counter() - start > 0.3  # held paused (the env waits) until P
    assert not d.takeover and not mentor.quit_requested and not mentor.paused and mentor.disconnects == 1
    assert mentor.screen is not None and pygame.display.get_surface() is mentor.screen  # reopened


@pytest.mark.timeout(30)
def test_gamepad_unplugged(env):
    # agent mode: control returns to the agent at once, the keyboard still drives
    mentor = mentor_for(env, "agent")
    post(pygame.JOYAXISMOTION, instance_id=7, axis=0, value=0.8)
    assert mentor.decide(env, AGENT).takeover
    post(pygame.JOYDEVICEREMOVED, instance_id=7)
    assert not mentor.decide(env, AGENT).takeover and mentor.disconnects == 1 and not mentor.paused
    post(pygame.KEYDOWN, key=pygame.K_UP)
    assert mentor.decide(env, AGENT).takeover
    post(pygame.KEYUP, key=pygame.K_UP)
    # pause mode: paused until a gamepad is plugged back in
    mentor = mentor_for(env, "pause")
    post(pygame.JOYAXISMOTION, instance_id=8, axis=0, value=0.8)
    assert mentor.decide(env, AGENT).takeover
    post(pygame.JOYDEVICEREMOVED, instance_id=8)
    post_later(400, pygame.JOYDEVICEADDED, device_index=99)
    start = time.perf_counter()
    d = mentor.decide(env, AGENT)
    assert time.perf_counter() - start > 0.3 and not d.takeover and not mentor.paused
    assert mentor.disconnects == 1 and mentor.input.pause_reason is None


def test_on_disconnect_from_the_recipe_config():
    cfg = load_config(overrides=["mentor.name=human", "mentor.kwargs.on_disconnect=pause", "mentor.kwargs.fps=0"])
    mentor = build_mentor(cfg)
    assert isinstance(mentor, HumanMentor) and mentor.input.pause_on_disconnect
    with pytest.raises(ConfigError, match=r"mentor.kwargs.on_disconnect='leave' is invalid: allowed: \['agent', "
                                          r"'pause'\]"):
        load_config(overrides=["mentor.name=human", "mentor.kwargs.on_disconnect=leave"])
    with pytest.raises(ConfigError, match="mentor.kwargs.colour=.*unknown HumanMentor argument"):
        load_config(overrides=["mentor.name=human", "mentor.kwargs.colour=red"])
    with pytest.raises(ValueError, match="on_disconnect='leave' is invalid"):
        HumanMentor(on_disconnect="leave")


def test_training_run_survives_a_closed_window_and_checkpoints_at_once(tmp_path, monkeypatch):
    """HACO with a person (headless): they hold the accelerator over steps 30-44, close the window at
    step 60; the agent drives the rest of the run, and a checkpoint at the end of that batch (75)
    holds every step so far, takeovers included."""
    script = {30: [(pygame.KEYDOWN, {"key": pygame.K_UP})], 45: [(pygame.KEYUP, {"key": pygame.K_UP})],
              60: [(pygame.WINDOWCLOSE, {})]}
    real = HumanMentor.decide
    seen = []

    def decide(self, env, agent_action):
        for kind, attrs in script.get(len(seen), []):
            post(kind, **attrs)
        seen.append(1)
        return real(self, env, agent_action)

    monkeypatch.setattr(HumanMentor, "decide", decide)
    out = tmp_path / "run"
    # HACO as recipes/haco runs it (the paper's loss, one uniform buffer: the rows in collection order below)
    final = train(out, "mentor.name=human", "mentor.kwargs.fps=0", "collector.realtime_hz=0",
                  "optim.async_updates=false", "physics.enabled=false", "loss.objective=paper", UNIFORM_REPLAY,
                  "collector.warmup_steps=0", "collector.total_frames=150", "checkpoint.every_frames=1000")
    assert final["training"]["frames"] == 150 and len(seen) == 150
    ckpt = out / "checkpoints" / "ckpt_000000075"
    assert (ckpt / "COMPLETE").is_file()  # written because the person left, not on a schedule
    cfg = load_config(out / "config.yaml", apply_profile=False)
    replay = builders.build_replay_buffer(cfg)
    load_checkpoint(ckpt, modules={}, optimizers={}, replay_buffers={"replay": replay}, strict=False,
                    restore_rng_state=False)
    assert len(replay) == 75
    takeovers = replay[:]["next", "intervention"].squeeze(-1)
    assert takeovers.nonzero().squeeze(-1).tolist() == list(range(30, 45))
    assert final["training"]["takeover_steps"] == 15  # after the window closed, the agent drove alone
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert [float(r["train/mentor_disconnects"]) for r in rows] == [0, 0, 1, 1, 1, 1]
