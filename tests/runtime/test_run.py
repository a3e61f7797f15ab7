"""Tests of ``pe_rlhf.runtime.run.Run`` with a learner that is no method of ours.

``Run`` knows no method: anything with the :class:`~pe_rlhf.runtime.run.Learner` hooks trains under it. The
learner here regresses the actor's ``loc`` onto a fixed target action from synthetic observations (one Adam
step per batch, ``BATCH`` frames a batch), so the tests can check what ``Run`` promises on its own: the
cadence of rows, evaluations and checkpoints; a resume that continues bit for bit; a non-finite loss that
keeps a checkpoint and says where; the finish (``actor.pt``, the final evaluation on the real driving env).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict

from pe_rlhf.envs import DrivingConfig
from pe_rlhf.envs.observation import observation_size
from pe_rlhf.modules.networks import make_actor
from pe_rlhf.runtime.checkpoint import list_checkpoints
from pe_rlhf.runtime.recipe import RunOptions, report_final
from pe_rlhf.durable import load_tensors
from pe_rlhf.runtime.run import ACTOR_FILE, Learner, Run, next_multiple

BATCH = 10
ENV = DrivingConfig(lidar_beams=8, horizon=20, min_blocks=1, max_blocks=1, split="train")
TARGET = torch.tensor([0.5, -0.25])

pytestmark = pytest.mark.usefixtures("one_thread")


class RegressionLearner(Learner):
    """The actor's ``loc`` pulled towards ``TARGET``; ``poison_at``: the loss turns NaN at that progress."""

    name, timers = "regression", ("collect", "update")

    def __init__(self, total: int, seed: int = 0, poison_at: int | None = None):
        torch.manual_seed(seed)
        self.env_config, self.total, self.poison_at = ENV, total, poison_at
        self.actor = make_actor(observation_size(ENV.lidar_beams, ENV.lane_features), hidden=(16,))
        self.optimizer = torch.optim.Adam(self.actor.parameters(), lr=1e-2)
        self.progress, self.updates = 0, 0

    def batches(self):
        while self.progress < self.total:
            obs = torch.randn(BATCH, observation_size(ENV.lidar_beams, ENV.lane_features))
            yield TensorDict({"observation": obs}, [BATCH])

    def learn(self, batch) -> dict[str, float]:
        loss = (self.actor.module[0](batch)["loc"] - TARGET).pow(2).mean()
        self.progress += BATCH
        if self.poison_at is not None and self.progress >= self.poison_at:
            loss = loss * float("nan")
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite loss at frame {self.progress}")
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        return {"loss": loss.item()}

    def checkpoint_objects(self, checkpoint=None) -> dict:
        return {"modules": {"actor": self.actor}, "optimizers": {"actor": self.optimizer}}

    def state_dict(self) -> dict:
        return {"updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.progress, self.updates = int(state["step"]), int(state["updates"])

    def summary(self, out_dir: Path) -> dict:
        return {"algorithm": "regression", "training": {"frames": self.progress, "updates": self.updates}}


class ListLogger:
    def __init__(self):
        self.rows: list[tuple[int, dict]] = []

    def log(self, step: int, metrics: dict) -> None:
        self.rows.append((step, dict(metrics)))

    def truncate_after(self, step: int) -> None:
        self.rows = [(s, m) for s, m in self.rows if s < step]


def _cfg(log_every: int = 1, keep: int = 10):
    return SimpleNamespace(eval=SimpleNamespace(split="train", episodes=1), checkpoint=SimpleNamespace(keep=keep),
                           logger=SimpleNamespace(log_every=log_every))


def _run(tmp_path, learner, logger=None, *, total=60, eval_every=0, checkpoint_every=20, log_every=1):
    return Run(_cfg(log_every), learner, logger or ListLogger(), tmp_path / "checkpoints", total=total,
               eval_every=eval_every, checkpoint_every=checkpoint_every)


def _params(module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def _steps(tmp_path) -> list[int]:
    """The steps of the checkpoints kept under the run's folder."""
    return [int(c.name.split("_")[1]) for c in list_checkpoints(tmp_path / "checkpoints")]


def test_next_multiple():
    assert next_multiple(0, 20) == 20 and next_multiple(20, 20) == 40 and next_multiple(39, 20) == 40
    assert next_multiple(5, 0) == float("inf")


def test_a_run_learns_and_keeps_its_cadence(tmp_path):
    logger = ListLogger()
    run = _run(tmp_path, RegressionLearner(total=60), logger, eval_every=30, checkpoint_every=20, log_every=4)
    final = run.train(tmp_path)
    steps = [s for s, _ in logger.rows]
    # a row every 4th batch (40), with each evaluation (30, 60) and the last (60)
    assert steps == [30, 40, 60]
    assert all("eval/success_rate_mean" in m for s, m in logger.rows if s in (30, 60))
    assert "eval/success_rate_mean" not in dict(logger.rows)[40]
    assert set(m["time/update_seconds"] >= 0 for _, m in logger.rows) == {True}
    assert _steps(tmp_path) == [20, 40, 60]
    # the finish: the final evaluation (1 episode) with the learner's summary and the timers, and actor.pt
    assert final["algorithm"] == "regression" and final["training"]["frames"] == 60
    assert final["training"]["update_s"] >= 0 and final["success_rate"]["mean"] in (0.0, 1.0)
    saved = load_tensors(tmp_path / ACTOR_FILE)[0]
    assert saved.keys() == run.learner.actor.state_dict().keys()
    # learning progress: the loss fell
    losses = [m["loss"] for _, m in logger.rows]
    assert losses[-1] < losses[0]


def test_resume_continues_bit_for_bit(tmp_path):
    whole = RegressionLearner(total=60)
    _run(tmp_path / "whole", whole, checkpoint_every=20).train(tmp_path / "whole")

    # the same run, cut after 40 frames (the session ends), then resumed into fresh objects
    cut = tmp_path / "cut"
    first = _run(cut, RegressionLearner(total=40), checkpoint_every=20)
    first.train(cut)
    logger = ListLogger()
    logger.rows = [(s, m) for s, m in first.logger.rows] + [(50, {"stale": 1.0})]  # logged after the checkpoint
    again = RegressionLearner(total=60, seed=123)  # other initial weights: all must come from the checkpoint
    resumed = _run(cut, again, logger, checkpoint_every=20)
    resumed.train(cut, resume=True)
    # torch.manual_seed is restored from the checkpoint, so the synthetic batches continue as they would have
    for k, v in _params(whole.actor).items():
        assert torch.equal(v, _params(again.actor)[k]), k
    assert again.updates == 6  # the learner's own state came back: 4 updates before the cut, 2 after
    assert [s for s, _ in logger.rows] == [10, 20, 30, 40, 50, 60] and "stale" not in dict(logger.rows)[50]


def test_resume_of_a_finished_run_evaluates_it_again(tmp_path, capsys):
    _run(tmp_path, RegressionLearner(total=20), checkpoint_every=20, total=20).train(tmp_path)
    learner = RegressionLearner(total=20, seed=5)
    final = _run(tmp_path, learner, checkpoint_every=20, total=20).train(tmp_path, resume=True)
    assert "already complete (20 of 20 frames)" in capsys.readouterr().out
    assert final["training"]["frames"] == 20


def test_resume_without_a_checkpoint_says_so_and_starts_over(tmp_path, capsys):
    final = _run(tmp_path, RegressionLearner(total=20)).train(tmp_path, resume=True)
    assert "no complete checkpoint yet; nothing was journaled either: the run starts over" in capsys.readouterr().out
    assert final["training"]["frames"] == 20


def test_a_non_finite_loss_keeps_a_checkpoint_and_says_where(tmp_path):
    run = _run(tmp_path, RegressionLearner(total=60, poison_at=30), checkpoint_every=100)
    where = r"non-finite loss at frame 30\. Saved checkpoint .*ckpt_0+30 \(frame 30.*--resume"
    with pytest.raises(FloatingPointError, match=where):
        run.train(tmp_path)
    assert _steps(tmp_path) == [30]
    assert not (tmp_path / ACTOR_FILE).exists()  # no finish after an error


def test_resume_refuses_another_env_config(tmp_path):
    _run(tmp_path, RegressionLearner(total=20), checkpoint_every=20, total=20).train(tmp_path)
    other = RegressionLearner(total=40)
    other.env_config = DrivingConfig(lidar_beams=8, horizon=30, min_blocks=1, max_blocks=1, split="train")
    with pytest.raises(ValueError, match=r"env\.horizon: checkpoint 20, now 30"):
        _run(tmp_path, other, total=40).train(tmp_path, resume=True)


FAST, STOP = torch.tensor([0.0, 3.0]), torch.tensor([0.0, -3.0])  # pre-tanh loc: full throttle, full brake


class SwitchingLearner(RegressionLearner):
    """Learns to drive (full throttle) until ``switch_at``, then to stand still: its middle actor is its best."""

    def __init__(self, total: int, switch_at: int, seed: int = 0):
        super().__init__(total, seed)
        self.switch_at = switch_at
        self.optimizer = torch.optim.Adam(self.actor.parameters(), lr=0.05)

    def learn(self, batch) -> dict[str, float]:
        target = FAST if self.progress < self.switch_at else STOP
        loss = (self.actor.module[0](batch)["loc"] - target).pow(2).mean()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.progress, self.updates = self.progress + BATCH, self.updates + 1
        return {"loss": loss.item()}


def _picking_run(tmp_path, learner, logger=None, *, total=300, every=50):
    cfg = _cfg()
    cfg.actor_selection = SimpleNamespace(every_frames=every, episodes=1, split="train")
    return Run(cfg, learner, logger or ListLogger(), tmp_path / "checkpoints", total=total, eval_every=0,
               checkpoint_every=50)


def test_the_actor_picked_on_train_scenes_is_the_best_snapshot_not_the_last(tmp_path, capsys):
    logger = ListLogger()
    learner = SwitchingLearner(total=300, switch_at=100)
    final = _picking_run(tmp_path, learner, logger).train(tmp_path)
    scores = {int(k): v["route_completion"] for k, v in final["actor_selection"]["scores"].items()}
    assert sorted(scores) == [50, 100, 150, 200, 250, 300]
    # the throttle actors drive further than the braking ones, and the best of them is the one kept
    assert min(scores[50], scores[100]) > max(scores[250], scores[300])
    picked = max(scores, key=lambda s: (scores[s], s))
    assert final["actor_selection"]["picked_step"] == picked and picked < 300
    # the final evaluation is the picked actor's; the last actor's stays beside it
    assert final["route_completion"]["mean"] > final["last_actor"]["route_completion"]["mean"]
    # scene by scene, so the two can be compared on any subset of the scenes
    assert [e["scene_seed"] for e in final["last_actor"]["episodes_detail"]] == [
        e["scene_seed"] for e in final["episodes_detail"]]
    # actor.pt holds the picked weights: those of the checkpoint at the picked step
    saved = load_tensors(tmp_path / ACTOR_FILE)[0]
    at_pick = torch.load(tmp_path / "checkpoints" / f"ckpt_{picked:09d}" / "tensors.pt", weights_only=True)
    for k, v in saved.items():
        assert torch.equal(v, at_pick["modules"]["actor"][k]), k
        assert not torch.equal(v, learner.actor.state_dict()[k]), k
    # each scoring adds its columns to a row
    rows = dict(logger.rows)
    assert rows[300]["actor_selection/picked_step"] == picked
    assert rows[50]["actor_selection/route_completion"] == scores[50]
    # the recipes' final table: the last actor's row above the picked one's, and which frames they are
    capsys.readouterr()
    # the recipe flags as a recipe passes them (no --compare, no --shield): RunOptions, not the fake config
    report_final(tmp_path, "regression", final, _cfg(), RunOptions())
    out = capsys.readouterr().out
    assert f"regression: the actor of frame {picked}, picked on 1 train scenes" in out
    assert "'last': the actor of frame 300" in out and out.index(" last ") < out.index(" regression ")


def test_a_resumed_run_picks_as_the_uninterrupted_one(tmp_path):
    whole = _picking_run(tmp_path / "whole", SwitchingLearner(total=300, switch_at=100))
    expected = whole.train(tmp_path / "whole")["actor_selection"]
    cut = tmp_path / "cut"
    _picking_run(cut, SwitchingLearner(total=150, switch_at=100), total=150).train(cut)
    again = _picking_run(cut, SwitchingLearner(total=300, switch_at=100, seed=7))
    got = again.train(cut, resume=True)["actor_selection"]
    assert got == expected
    for k, v in load_tensors(tmp_path / "whole" / ACTOR_FILE)[0].items():
        assert torch.equal(v, load_tensors(cut / ACTOR_FILE)[0][k]), k


@pytest.mark.parametrize("picking_before", [False, True])
def test_resume_refuses_to_switch_actor_selection_midway(tmp_path, picking_before):
    cut = tmp_path / "cut"
    first = _picking_run if picking_before else (lambda d, learner, total: _run(d, learner, total=total,
                                                                               checkpoint_every=50))
    first(cut, SwitchingLearner(total=150, switch_at=100), total=150).train(cut)
    then = (lambda d, learner: _run(d, learner, total=300, checkpoint_every=50)) if picking_before else _picking_run
    was, now = ("on", "off") if picking_before else ("off", "on")
    with pytest.raises(ValueError, match=f"written with actor_selection {was}, this run has it {now}.*config.yaml"):
        then(cut, SwitchingLearner(total=300, switch_at=100)).train(cut, resume=True)


def test_actor_selection_picks_on_train_scenes(tmp_path):
    """The config has no split to give (issue 43): a run picks its actor on the first train scenes, always."""
    cfg = _cfg()
    cfg.actor_selection = SimpleNamespace(every_frames=50, episodes=3)
    run = Run(cfg, RegressionLearner(total=50), ListLogger(), None, total=50, eval_every=0, checkpoint_every=0)
    assert (run.selection.split, run.selection.episodes, run.selection.every) == ("train", 3, 50)
