"""The RL and safe-RL baseline recipes (SAC-RS, SAC-Lag, PPO-RS, PPO-Lag, CPO) on the driving env.

Each recipe trains its smoke profile (300 env steps, 32x32 networks, horizon 50, one test episode) and
must write every output with finite numbers; SAC-Lag's multiplier is checked step by step against the
projected dual ascent on the logged episode-cost window (cost limit 0, so every cost raises it); bad
config values fail naming the field; every smoke run moves every actor parameter and a parameter of every
optimiser; the command line applies overrides; ``--resume`` continues a run.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from pe_rlhf.algorithms.baselines import (METHODS, EpisodeTracker, default_config, load_baseline_actor,
                                          load_baseline_config, main)
from pe_rlhf.algorithms.baselines.loop import compact_copy
from pe_rlhf.evaluation import TorchRLPolicyAdapter
from pe_rlhf.evaluation.evaluate import MEAN_STD_METRICS
from pe_rlhf.runtime.checkpoint import load_checkpoint
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.metrics_logger import read_metrics_csv
from pe_rlhf.runtime.world import obs_dim
from _learning import assert_trained, watched_main
from _scripts import SCRIPT_ENV

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore::FutureWarning"), pytest.mark.filterwarnings("ignore::UserWarning")]

ROOT = Path(__file__).resolve().parents[3]
SMOKE_FRAMES = 300
OUTPUTS = ("config.yaml", "metrics.csv", "final_eval.json", "learning_curves.png", "actor.safetensors")
SIX_METRICS = ("episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
               "overtake_count")
# SAC-Lag runs with cost limit 0 and a large step, so that every training cost moves lambda visibly.
LAMBDA_LR = 0.5
# The dual ascent needs costs in its 300 smoke steps: the 250-float world (no lane summary) has them at seed 0.
EXTRA = {"sac_lag": ["constraint.cost_limit=0", f"constraint.lambda_lr={LAMBDA_LR}", "env.lane_features=false"]}


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory):
    """``smoke_runs(method)``: the run folder of ``train.py profile=smoke`` and its parameters before and after
    training (``watched_main``), once per module."""
    done: dict[str, tuple[Path, dict]] = {}

    def run(method: str) -> tuple[Path, dict]:
        if method not in done:
            out = tmp_path_factory.mktemp(method)
            done[method] = out, watched_main(method, ["profile=smoke", *EXTRA.get(method, []), "--out", str(out)])
        return done[method]

    return run


@pytest.fixture(scope="module")
def smoke_run(smoke_runs):
    """``smoke_run(method)``: the run folder of ``smoke_runs(method)``."""
    return lambda method: smoke_runs(method)[0]


def check_outputs(out: Path, method: str) -> list[dict[str, float]]:
    """Every output file exists and holds finite numbers; returns the metrics rows."""
    for name in OUTPUTS:
        assert (out / name).is_file(), f"{method}: {name} missing"
    assert (out / "learning_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    cfg = load_baseline_config(method, out / "config.yaml", apply_profile=False)
    assert cfg.method == method and cfg.profile == "smoke"

    columns, rows = read_metrics_csv(out / "metrics.csv")
    assert rows and all(math.isfinite(v) for row in rows for v in row.values())
    assert [r["env_steps"] for r in rows] == sorted({r["env_steps"] for r in rows})
    assert rows[-1]["env_steps"] == SMOKE_FRAMES
    needed = ["wall_time", "train/episode_return", "train/episode_cost", "train/safety_violations_total",
              "train/success_rate_total"] + (["train/lambda"] if METHODS[method].lagrangian else [])
    assert set(needed) <= set(columns), f"{method}: {set(needed) - set(columns)} not logged"
    assert any(c.startswith("loss/") for c in columns)
    violations = [r["train/safety_violations_total"] for r in rows]
    assert violations == sorted(violations)  # cumulative

    final = OmegaConf.to_container(OmegaConf.load(out / "final_eval.json"))
    assert final["method"] == METHODS[method].name and final["episodes"] == 1
    assert all(math.isfinite(final[k]["mean"]) for k in SIX_METRICS + MEAN_STD_METRICS)
    assert final["training"]["env_steps"] == SMOKE_FRAMES
    assert final["training"]["safety_violations"] == violations[-1]

    actor = load_baseline_actor(out)  # actor.pt, weights_only, into make_actor
    action = TorchRLPolicyAdapter(actor)(np.zeros(obs_dim(cfg), dtype=np.float32), None)
    assert action.shape == (2,) and bool((np.abs(action) <= 1).all())
    return rows


# --------------------------------------------------------------------------- configs


@pytest.mark.parametrize("method", list(METHODS))
def test_recipe_config_yaml_composes_the_structured_config_and_shows_its_values(method):
    """The file's defaults list names the schema and the profile; its values are the schema's defaults, every one
    shown (tests/algorithms/test_recipe_config_files.py)."""
    recipe = ROOT / "recipes" / method / "config.yaml"
    shown = OmegaConf.to_container(OmegaConf.load(recipe))
    assert shown.pop("defaults") == [f"{method}_schema", "_self_", {"profile": "paper"}]
    assert shown == {k: v for k, v in default_config(method).items() if k != "profile"}
    assert OmegaConf.to_container(load_baseline_config(method, recipe)) == default_config(method)


@pytest.mark.parametrize("method, override, field", [
    ("sac_rs", "optim.lr=-1", "optim.lr"),
    ("sac_rs", "collector.learning_starts=300", "collector.learning_starts"),  # smoke: total_frames 300
    ("sac_lag", "constraint.cost_limit=-0.5", "constraint.cost_limit"),
    ("sac_lag", "loss.cost_aggregate=median", "loss.cost_aggregate"),
    ("ppo_rs", "optim.minibatch_size=1000", "optim.minibatch_size"),  # > collector.frames_per_batch
    ("ppo_lag", "loss.gae_lambda=1.5", "loss.gae_lambda"),
    ("cpo", "loss.backtrack_ratio=1", "loss.backtrack_ratio"),
    ("cpo", "env.horizon=0", "env.horizon"),
    ("sac_rs", "constraint.cost_limit=1", "constraint.cost_limit"),  # RS methods have no constraint
    ("ppo_rs", "loss.tau=0.1", "loss.tau"),  # a SAC field on PPO
    ("cpo", "eval.episodes=51", "eval.episodes"),  # the test split has 50 scenes
])
def test_bad_config_value_fails_naming_the_field(method, override, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")) as err:
        load_baseline_config(method, overrides=["profile=smoke", override])
    assert err.value.field == field


def test_bad_config_value_stops_the_command_line_before_training(tmp_path):
    with pytest.raises(ConfigError, match=r"optim\.epochs"):
        main("ppo_lag", ["profile=smoke", "optim.epochs=0", "--out", str(tmp_path / "run")])
    assert not (tmp_path / "run").exists()


def test_episode_tracker_carries_episodes_across_batches():
    def batch(rewards, costs, dones, successes):
        col = lambda v, dtype: torch.tensor(v, dtype=dtype).unsqueeze(-1)
        nxt = {"reward": col(rewards, torch.float32), "cost": col(costs, torch.float32),
               "done": col(dones, torch.bool), "success": col(successes, torch.bool)}
        return TensorDict({"next": nxt}, [len(dones)])

    tracker = EpisodeTracker(window=2)
    first = tracker.add(batch([1, 2, 3], [0, 1, 0], [0, 1, 0], [0, 0, 0]))
    assert first.returns == [3.0] and first.costs == [1.0] and tracker.window_cost() == 1.0
    second = tracker.add(batch([4, 5, 6], [1, 1, 0], [1, 0, 1], [1, 0, 0]))  # the open episode ends at once
    assert second.returns == [7.0, 11.0] and second.costs == [1.0, 1.0] and second.successes == [True, False]
    assert tracker.window_cost() == 1.0 and len(tracker.window) == 2
    assert (tracker.episodes, tracker.successes, tracker.safety_violations) == (3, 1, 3.0)
    restored = EpisodeTracker(window=2)
    restored.load_state_dict(tracker.state_dict())
    assert restored.state_dict() == tracker.state_dict()


def test_checkpoint_copy_of_a_replay_buffer_holds_its_items_oldest_first():
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    buffer.extend(TensorDict({"x": torch.arange(4.0)}, [4]))
    copy = compact_copy(buffer)
    assert copy.storage.max_size == 4 and torch.equal(copy.storage[:4]["x"], torch.arange(4.0))
    buffer.extend(TensorDict({"x": torch.arange(4.0, 13.0)}, [9]))  # wrapped: slots hold 10, 11, 12, 3, ..., 9
    assert torch.equal(compact_copy(buffer).storage[:10]["x"], torch.arange(3.0, 13.0))
    assert len(compact_copy(TensorDictReplayBuffer(storage=LazyTensorStorage(10)))) == 0


# --------------------------------------------------------------------------- smoke runs


@pytest.mark.parametrize("method", ["sac_rs", "sac_lag", "ppo_lag", "cpo"])
def test_smoke_run_writes_every_output(smoke_run, method):
    check_outputs(smoke_run(method), method)


@pytest.mark.parametrize("method", ["sac_rs", "sac_lag", "ppo_rs", "ppo_lag", "cpo"])
def test_every_rl_baseline_trains_its_actor_and_every_optimiser(smoke_runs, method):
    """Issue 45, case 10: in the smoke run every actor parameter moved, and a parameter of every optimiser."""
    assert_trained(method, smoke_runs(method)[1])


def assert_dual_ascent(out: Path) -> list[dict[str, float]]:
    """Cost limit 0: from learning start on, each batch's lambda is the previous one plus
    ``lambda_lr * window cost`` (the mean cost of the last finished episodes, logged in the same row)."""
    _, rows = read_metrics_csv(out / "metrics.csv")
    cfg = load_baseline_config("sac_lag", out / "config.yaml", apply_profile=False)
    assert (cfg.constraint.cost_limit, cfg.constraint.lambda_lr) == (0.0, LAMBDA_LR)
    lam = 0.0
    for row in rows:
        if row["env_steps"] >= cfg.collector.learning_starts and "train/episode_cost_window" in row:
            lam = max(lam + LAMBDA_LR * row["train/episode_cost_window"], 0.0)
        assert row["train/lambda"] == pytest.approx(lam, abs=1e-6), row["env_steps"]
    return rows


def test_sac_lag_lambda_rises_by_projected_dual_ascent_on_the_cost_window(smoke_run):
    rows = assert_dual_ascent(smoke_run("sac_lag"))
    assert rows[-1]["train/safety_violations_total"] > 0  # cost occurred ...
    assert rows[-1]["train/lambda"] > 0.1  # ... and the multiplier rose


def test_command_line_applies_overrides(tmp_path):
    """``recipes/ppo_rs/train.py profile=smoke optim.lr=...`` as a user runs it (PPO-RS's smoke test)."""
    out = tmp_path / "ppo_rs"
    env = {**os.environ, "PYTHONPATH": SCRIPT_ENV["PYTHONPATH"], "SDL_VIDEODRIVER": "dummy", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "ppo_rs" / "train.py"), "profile=smoke",
                           "optim.lr=0.000321", "loss.clip_epsilon=0.3", "--out", str(out)],
                          env=env, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = load_baseline_config("ppo_rs", out / "config.yaml", apply_profile=False)
    assert (cfg.optim.lr, cfg.loss.clip_epsilon, cfg.optim.epochs) == (0.000321, 0.3, 2)  # epochs: smoke's
    check_outputs(out, "ppo_rs")


def test_resume_continues_from_the_last_checkpoint(tmp_path):
    """A 200-step SAC-Lag run continued to 300: one row per batch, lambda and the cost window carried over
    (the dual ascent holds across the resume), the replay buffer restored."""
    out = tmp_path / "run"
    main("sac_lag", ["profile=smoke", *EXTRA["sac_lag"], "collector.total_frames=200", "--out", str(out)])
    main("sac_lag", ["--resume", str(out), "collector.total_frames=300"])
    rows = assert_dual_ascent(out)
    assert [r["env_steps"] for r in rows] == [50, 100, 150, 200, 250, 300]
    assert rows[3]["train/lambda"] > 0  # the resumed part started from a raised lambda
    assert (out / "checkpoints" / "latest").read_text().strip() == "ckpt_000000300"
    assert OmegaConf.load(out / "final_eval.json").training.env_steps == 300
    checkpoint = load_checkpoint(out / "checkpoints", modules={}, optimizers={}, strict=False, restore_rng_state=False)
    assert checkpoint["buffer_lengths"] == {"replay": 300}  # the 200 restored plus the 100 collected since
