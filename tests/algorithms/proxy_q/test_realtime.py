"""Human-paced training: the real-time step clock, the learner beside acting, and the recipe with both."""

from __future__ import annotations

import csv
import math
import sys
import threading
import time

import pytest
import torch
from tensordict import TensorDict
from _scripts import load_pe_rlhf_recipe

from pe_rlhf.objectives.perlhf import make_transitions
from pe_rlhf.runtime.config import save_config
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.background_updates import (
    BackgroundUpdater,
    SyncUpdater,
    make_interaction_type_thread_local,
)
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.transforms import RealtimePacing

FRAME_COLUMNS = ("time/frame_ms_mean", "time/frame_jitter_ms_p95", "time/frame_jitter_ms_max")


# --------------------------------------------------------------------------- RealtimePacing


@pytest.mark.timing
def test_pacing_holds_the_rate_across_resets():
    from torchrl.envs import GymEnv

    pacing = RealtimePacing(hz=10)  # 100 ms: long against a busy CI machine's oversleep
    env = GymEnv("Pendulum-v1").append_transform(pacing)
    env.set_seed(0)
    env.rollout(11)
    env.reset()  # the clock keeps running through resets
    env.rollout(10, break_when_any_done=False)
    stats = pacing.frame_stats()
    assert stats["frames"] == 20  # the first step starts the clock
    assert abs(stats["frame_ms_mean"] - 100.0) <= 10.0, stats
    assert stats["frame_ms_p50"] == pytest.approx(100.0, abs=10.0)
    assert set(stats) >= {f"{k}_{s}" for k in ("frame_ms", "jitter_ms")
                          for s in ("mean", "std", "p50", "p95", "p99", "max")} | {"late_frames"}
    assert pacing.frame_stats(last=5)["frames"] == 5


@pytest.mark.timing
def test_clock_is_deadline_based_and_reanchors_after_a_stall():
    # Periods long against scheduler noise (a busy 2-core CI machine oversleeps by ~10-20 ms).
    pacing = RealtimePacing(hz=10)  # 100 ms
    start = pacing.wait_for_tick()
    time.sleep(0.06)  # 60 ms of work: the tick still comes at +100 ms, not +160 ms
    assert pacing.wait_for_tick() - start == pytest.approx(0.100, abs=0.03)
    time.sleep(0.5)  # a stall of five periods: one late frame, then the clock restarts from it
    stalled = pacing.wait_for_tick()
    after = pacing.wait_for_tick()
    assert after - stalled == pytest.approx(0.100, abs=0.03)  # no burst of catch-up frames
    stats = pacing.frame_stats()
    assert stats["frames"] == 3 and stats["late_frames"] == 1
    assert stats["jitter_ms_max"] >= 400  # the stalled frame: ~560 ms for a 100 ms period


@pytest.mark.parametrize("hz", [0, -10, float("nan"), float("inf"), True, "10"])
def test_invalid_hz_raises_naming_hz(hz):
    with pytest.raises(ValueError, match="hz"):
        RealtimePacing(hz=hz)


def test_no_frames_gives_nan_statistics():
    stats = RealtimePacing(10).frame_stats()
    assert stats["frames"] == 0 and math.isnan(stats["jitter_ms_p95"])


# --------------------------------------------------------------------------- the learner


def _learner_parts(rows: int = 64):
    cfg = load_config(overrides=["profile=smoke"])
    torch.manual_seed(0)
    actor = builders.build_actor(cfg)
    loss, soft_update = builders.build_loss(cfg, actor)
    optimizers = builders.build_optimizers(cfg, loss)
    replay = builders.build_replay_buffer(cfg)
    g = torch.Generator().manual_seed(0)
    agent = torch.rand(rows, 2, generator=g) * 2 - 1
    intervention = torch.rand(rows, 1, generator=g) < 0.3
    replay.extend(make_transitions(torch.rand(rows, obs_dim(cfg), generator=g),
                                   torch.rand(rows, obs_dim(cfg), generator=g), agent,
                                   torch.where(intervention, -agent, agent), intervention, intervention,
                                   torch.zeros(rows, 1, dtype=torch.bool)))
    return actor, loss, soft_update, optimizers, replay


def _weights(module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def test_background_updater_keeps_the_update_to_data_ratio(one_thread):
    actor, loss, soft_update, optimizers, replay = _learner_parts()
    updater = BackgroundUpdater(loss, optimizers, soft_update, replay, updates_per_step=0.5, max_grad_norm=10.0,
                                actor=actor, threads=1, publish_every=2)
    acting_before = _weights(updater.acting_actor)
    switch_interval = sys.getswitchinterval()
    with updater:
        assert sys.getswitchinterval() <= 0.001  # the acting thread gets the GIL back sooner
        updater.notify_frames(10)
        deadline = time.time() + 20
        while updater.updates_done < 5 and time.time() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
        assert updater.updates_done == 5  # never ahead of the data
        assert set(updater.latest_losses()) >= {"loss_qvalue", "loss_actor"}
        width = obs_dim(load_config(overrides=["profile=smoke"]))
        acted = updater.policy(TensorDict({"observation": torch.zeros(width)}))
        assert acted.get("action").shape == (2,)
        updater.notify_frames(27)  # 37 frames: floor(18.5) updates
    assert updater.updates_done == 18  # stop (leaving the block) runs the owed updates first
    assert sys.getswitchinterval() == switch_interval
    assert updater.backlog == 0
    # the acting copy holds the learner's final weights, and they moved
    for acting, learner, before in zip(_weights(updater.acting_actor), _weights(actor), acting_before):
        assert torch.equal(acting, learner)
    assert any(not torch.equal(a, b) for a, b in zip(_weights(actor), acting_before))
    assert updater.policy.actor is updater.acting_actor and updater.acting_actor is not actor


def test_stop_without_finishing_leaves_owed_updates(one_thread):
    actor, loss, soft_update, optimizers, replay = _learner_parts()
    updater = BackgroundUpdater(loss, optimizers, soft_update, replay, updates_per_step=1, max_grad_norm=None,
                                actor=actor, threads=1)
    updater.start()
    updater.notify_frames(100_000)
    updater.stop(finish=False)
    assert 0 <= updater.updates_done < 100_000 and updater._thread is None


def test_thread_error_is_raised_in_the_caller(monkeypatch, one_thread):
    def failing_update(*args, **kwargs):
        raise FloatingPointError("loss_qvalue is nan (not finite): updates stopped")

    monkeypatch.setattr("pe_rlhf.algorithms.proxy_q.background_updates.update", failing_update)
    actor, loss, soft_update, optimizers, replay = _learner_parts()
    updater = BackgroundUpdater(loss, optimizers, soft_update, replay, updates_per_step=1, max_grad_norm=None,
                                actor=actor, threads=1)
    with pytest.raises(FloatingPointError, match="loss_qvalue"), updater:
        updater.notify_frames(3)
        deadline = time.time() + 10
        while updater._thread.is_alive() and time.time() < deadline:
            time.sleep(0.01)
        updater.notify_frames(1)  # the next call re-raises the thread's error
    with pytest.raises(FloatingPointError):
        updater.latest_losses()


def test_sync_updater_runs_the_owed_updates_inline(one_thread):
    actor, loss, soft_update, optimizers, replay = _learner_parts()
    updater = SyncUpdater(loss, optimizers, soft_update, replay, updates_per_step=5 / 50, max_grad_norm=10.0,
                          actor=actor, threads=1)
    with updater:
        for _ in range(3):
            updater.notify_frames(50)
        assert updater.updates_done == 15 and updater.backlog == 0  # 5 per 50 frames exactly (1/10, no float drift)
        with updater.paused():
            pass
    assert updater.policy is actor and "loss_actor" in updater.latest_losses()


def test_exploration_type_is_per_thread():
    from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type

    make_interaction_type_thread_local()
    inside, release = threading.Event(), threading.Event()

    def other_thread():
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            inside.set()
            release.wait(5)

    with set_exploration_type(ExplorationType.RANDOM):
        thread = threading.Thread(target=other_thread)
        thread.start()
        inside.wait(5)
        assert exploration_type() == ExplorationType.RANDOM  # the other thread's context does not leak here
        release.set()
        thread.join()
        assert exploration_type() == ExplorationType.RANDOM


# --------------------------------------------------------------------------- config and the recipe


def test_human_mentor_defaults_are_applied_unless_given(tmp_path):
    cfg = load_config()
    assert (cfg.collector.realtime_hz, cfg.optim.async_updates) == (0, False)
    human = load_config(overrides=["mentor.name=human"])
    assert (human.collector.realtime_hz, human.optim.async_updates) == (10.0, True)
    saved = load_config(save_config(human, tmp_path / "config.yaml"), apply_profile=False)
    assert (saved.collector.realtime_hz, saved.optim.async_updates) == (10.0, True)  # the saved config shows them
    given = load_config(overrides=["mentor.name=human", "collector.realtime_hz=0", "optim.async_updates=false"])
    assert (given.collector.realtime_hz, given.optim.async_updates) == (0, False)
    assert load_config(save_config(given, tmp_path / "g.yaml"), apply_profile=False).collector.realtime_hz == 0


@pytest.mark.parametrize("overrides, field", [
    (["collector.realtime_hz=-1"], "collector.realtime_hz"),
    (["optim.async_updates=sometimes"], "optim.async_updates"),
    (["collector.backend=multisync", "collector.num_workers=2", "optim.async_updates=true"], "optim.async_updates"),
    (["collector.backend=multisync", "collector.num_workers=2", "collector.realtime_hz=10"], "collector.realtime_hz"),
])
def test_invalid_pacing_and_async_settings_name_the_field(overrides, field):
    with pytest.raises(ConfigError) as info:
        load_config(overrides=overrides)
    assert info.value.field == field and field in str(info.value)


@pytest.mark.timing
def test_recipe_with_async_updates_and_pacing_logs_frame_times(tmp_path):
    final = load_pe_rlhf_recipe().main(["profile=smoke", "optim.async_updates=true", "collector.realtime_hz=25",
                                 "eval.every_frames=0", "checkpoint.every_frames=150", "--out", str(tmp_path)])
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(float(r["step"])) for r in rows] == [50, 100, 150, 200, 250, 300]
    for row in rows:
        for key in FRAME_COLUMNS:
            assert math.isfinite(float(row[key])), key
        for key, value in row.items():
            if value != "":
                assert math.isfinite(float(value)), key
    # 25 Hz, 2.5 times a person's 10: at 50 Hz a frame's work (env step, physics, the forecast during a takeover)
    # sometimes outran its 20 ms on 2 CI cores (26.9 ms mean, twice in six runs), so the pacing was not what was tested
    # paced: never faster than 40 ms a frame; slower only where a frame's work outruns it (47 ms after the suite)
    assert 35.0 < float(rows[-1]["time/frame_ms_mean"]) < 80.0  # 25 Hz
    assert any(r.get("loss/qvalue") for r in rows)
    assert final["training"]["updates"] == 30  # 5 per 50 frames from learning_starts on, as the sync loop
    assert (tmp_path / "checkpoints").exists()
