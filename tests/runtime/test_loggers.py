"""Metrics through TorchRL's ``Logger`` interface: the crash-safe CSV, and wandb / TensorBoard / MLflow
fed by :class:`MetricsLogger` (real packages, offline, in a tmp dir; each skipped when not installed)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.record.loggers import Logger

from pe_rlhf.runtime.csv_logger import CrashSafeCSVLogger
from pe_rlhf.runtime.metrics_logger import MetricsLogger


def _rows(path) -> list[list[str]]:
    return [line.split(",") for line in path.read_text().splitlines()]


def _tensorboard_events(log_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0})
    events.Reload()
    return events


@pytest.fixture
def offline_wandb(monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_API_KEY", "")  # no credentials, and a closed local port as the server
    monkeypatch.setenv("WANDB_BASE_URL", "http://127.0.0.1:9")


def test_crash_safe_csv_through_the_torchrl_interface(tmp_path):
    logger = CrashSafeCSVLogger("run", tmp_path / "a")
    assert isinstance(logger, Logger)
    logger.log_metrics({"train/takeover_rate": 0.5, "loss/qvalue": torch.tensor(1.25)}, step=100)
    logger.log_scalar("eval/success_rate_mean", 1, step=200)
    logger.log_metrics(TensorDict({"loss": {"qvalue": torch.tensor(0.75)}}, []), step=300)  # keys joined by "/"
    logger.log_metrics({"train/takeover_rate": float("nan")}, step=400)  # non-finite: a blank cell
    logger.log_video("eval/test_episode", torch.zeros(1, 2, 3, 4, 4, dtype=torch.uint8), step=400)  # not a scalar
    logger.log_hparams({"lr": 1e-4})
    with pytest.raises(NotImplementedError):
        logger.log_histogram("h", [1.0, 2.0], step=1)
    logger.shutdown()
    assert not logger.is_alive
    with pytest.raises(RuntimeError, match="closed"):
        logger.log_scalar("x", 1.0, step=500)
    path = tmp_path / "a" / "metrics.csv"
    assert _rows(path) == [["step", "train/takeover_rate", "loss/qvalue", "eval/success_rate_mean"],
                           ["100", "0.5", "1.25", ""], ["200", "", "", "1"], ["300", "", "0.75", ""],
                           ["400", "", "", ""]]
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["metrics.csv"]  # no videos, no temp files
    assert path.stat().st_mode & 0o777 == 0o644  # readable by others, like every output (not mkstemp's 0600)

    with MetricsLogger(tmp_path / "b") as same:  # MetricsLogger writes the very same bytes through it
        same.log(100, {"train/takeover_rate": 0.5, "loss/qvalue": torch.tensor(1.25)})
        same.log(200, {"eval/success_rate_mean": 1})
        same.log(300, {"loss/qvalue": 0.75})
        with pytest.warns(RuntimeWarning, match="not finite"):
            same.log(400, {"train/takeover_rate": float("nan")})
        assert isinstance(same.loggers["csv"], CrashSafeCSVLogger)
    assert (tmp_path / "b" / "metrics.csv").read_bytes() == path.read_bytes()


def test_crash_safe_csv_resume_truncates_the_replayed_rows(tmp_path):
    with CrashSafeCSVLogger("run", tmp_path) as logger:
        for step in (100, 200, 300, 400):
            logger.log_scalar("train/takeover_rate", step / 1000, step=step)
        logger.log_metrics({"eval/episodic_return_mean": 5.0}, step=300)
    # a checkpoint at step 300: its run logs 300 and later again
    with CrashSafeCSVLogger("run", tmp_path, resume=True) as logger:
        assert logger.columns == ["step", "train/takeover_rate", "eval/episodic_return_mean"]
        assert logger.truncate_after(300) == 3 and logger.last_step == 200
        logger.log_scalar("train/takeover_rate", 0.9, step=300)
    assert _rows(tmp_path / "metrics.csv") == [["step", "train/takeover_rate", "eval/episodic_return_mean"],
                                               ["100", "0.1", ""], ["200", "0.2", ""], ["300", "0.9", ""]]
    with CrashSafeCSVLogger("run", tmp_path) as logger:  # without resume the file is replaced
        logger.log_scalar("x", 1.0, step=1)
    assert _rows(tmp_path / "metrics.csv") == [["step", "x"], ["1", "1.0"]]


def test_wandb_and_tensorboard_receive_scalars_and_the_test_episode_video(tmp_path, offline_wandb):
    pytest.importorskip("tensorboard")
    pytest.importorskip("moviepy")  # video encoding for both
    from torchrl.record.loggers import TensorboardLogger, WandbLogger

    from pe_rlhf.evaluation import make_policy
    from pe_rlhf.runtime.video import CAPTION_HEIGHT, record_episode_gif

    video = record_episode_gif(make_policy("idm-mobil", 0), None, 1000, tmp_path / "episode.gif", max_steps=5,
                               keep_video=True)["video"]
    assert video.dtype == np.uint8 and video.shape == (6, 338 + CAPTION_HEIGHT, 600, 3)  # the GIF's captioned frames
    with MetricsLogger(tmp_path, backends=["csv", "wandb", "tensorboard"], config={"lr": 1e-4}) as logger:
        logger.log(1, {"train/takeover_rate": 0.5, "loss/qvalue": 2.0})
        logger.log(2, {"train/takeover_rate": 0.25})
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # both take the video
            logger.log_video("eval/test_episode", video, step=2)
        assert isinstance(logger.loggers["wandb"], WandbLogger) and logger.wandb_run.offline
        assert isinstance(logger.loggers["tensorboard"], TensorboardLogger)
    events = _tensorboard_events(tmp_path / "tensorboard")
    assert [(e.step, e.value) for e in events.Scalars("train/takeover_rate")] == [(1, 0.5), (2, 0.25)]
    assert [e.step for e in events.Scalars("loss/qvalue")] == [1]
    assert [(e.step, e.width, e.height) for e in events.Images("eval/test_episode")] == [(2, 600, 338 + CAPTION_HEIGHT)]
    (run,) = (tmp_path / "wandb").glob("offline-run-*")
    assert list(run.glob("run-*.wandb")) and list(run.glob("files/media/videos/eval/test_episode_2_*.mp4"))
    assert len(_rows(tmp_path / "metrics.csv")) == 3


def test_tensorboard_resume_purges_the_replayed_steps(tmp_path):
    pytest.importorskip("tensorboard")
    with MetricsLogger(tmp_path, backends=["csv", "tensorboard"]) as logger:
        for step in (1, 2, 3, 4):
            logger.log(step, {"train/takeover_rate": step / 10})
    with MetricsLogger(tmp_path, backends=["csv", "tensorboard"], resume=True) as logger:
        assert logger.truncate_after(3) == 2
        logger.log(3, {"train/takeover_rate": 0.9})
    events = _tensorboard_events(tmp_path / "tensorboard")
    assert [(e.step, round(e.value, 6)) for e in events.Scalars("train/takeover_rate")] == [(1, 0.1), (2, 0.2),
                                                                                           (3, 0.9)]


def test_mlflow_receives_scalars_and_the_config(tmp_path, monkeypatch):
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient
    from torchrl.record.loggers import MLFlowLogger

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)  # the run folder's own file store
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    out = tmp_path / "run-1"
    with MetricsLogger(out, backends=["csv", "mlflow"], config={"optim": {"lr": 1e-4}, "seed": 0}) as logger:
        assert isinstance(logger.loggers["mlflow"], MLFlowLogger)
        logger.log(1, {"train/takeover_rate": 0.5})
        logger.log(2, {"train/takeover_rate": 0.25})
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # without torchcodec MLflow takes no video
            logger.log_video("eval/test_episode", np.zeros((2, 8, 8, 3), np.uint8), step=2)
    client = MlflowClient((out / "mlruns").resolve().as_uri())
    (run,) = client.search_runs([client.get_experiment_by_name("pe-rlhf").experiment_id])
    assert run.info.status == "FINISHED" and run.info.run_name == "run-1"
    history = client.get_metric_history(run.info.run_id, "train/takeover_rate")
    assert [(m.step, m.value) for m in history] == [(1, 0.5), (2, 0.25)]
    assert run.data.params == {"optim.lr": "0.0001", "seed": "0"}
