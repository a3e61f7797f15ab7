"""Training metrics through TorchRL's ``Logger`` interface: a crash-safe CSV, and wandb, TensorBoard, MLflow.

:class:`MetricsLogger` fans each :meth:`~MetricsLogger.log` call out to the TorchRL loggers it was
configured with (:attr:`MetricsLogger.loggers`): the crash-safe CSV
(:class:`~pe_rlhf.runtime.csv_logger.CrashSafeCSVLogger`, one row per call: ``step`` (environment
steps) plus the given metrics) and TorchRL's own ``WandbLogger``, ``TensorboardLogger`` and
``MLFlowLogger``; :meth:`~MetricsLogger.log_video` sends a video (the test episode) to the ones that
take videos. Column names follow the convention in :mod:`pe_rlhf.runtime.plots` (``train/...``,
``loss/...``, ``eval/<metric>_mean`` / ``eval/<metric>_std``); :func:`flatten_eval_summary` turns an
evaluation summary into the ``eval/`` columns.
"""

from __future__ import annotations

import csv
import math
import os
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

from torchrl.record.loggers.tensorboard import TensorboardLogger

from pe_rlhf.runtime.config_rules import LOGGER_BACKENDS
from pe_rlhf.runtime.csv_logger import CSV_NAME, STEP, CrashSafeCSVLogger, to_number

VIDEO_FPS = 10  # the test-episode GIF's rate: the env's 10 Hz policy, real time


def flatten_eval_summary(summary: Mapping[str, Any], prefix: str = "eval/") -> dict[str, float]:
    """Evaluation summary ``{metric: {"mean", "std"}}`` -> ``{f"{prefix}{metric}_mean" | "_std": x}``.

    Entries that are not mean/std dicts (``episodes``, ``seeds``, ...) are skipped.
    """
    out: dict[str, float] = {}
    for key, stat in summary.items():
        if isinstance(stat, Mapping) and "mean" in stat and "std" in stat:
            out[f"{prefix}{key}_mean"] = float(stat["mean"])
            out[f"{prefix}{key}_std"] = float(stat["std"])
    return out


def read_metrics_csv(path: str | os.PathLike) -> tuple[list[str], list[dict[str, float]]]:
    """The columns and rows of a metrics CSV; blank or unparsable cells are left out of a row."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        columns = list(reader.fieldnames or [])
        rows = []
        for raw in reader:
            row: dict[str, float] = {}
            for key, text in raw.items():
                if key is None or text in (None, ""):
                    continue
                try:
                    row[key] = float(text)
                except ValueError:
                    continue
            rows.append(row)
    return columns, rows


def wandb_mode() -> str:
    """The mode a wandb run starts in: wandb's own ``$WANDB_MODE`` where a user set it, else ``offline``."""
    return os.environ.get("WANDB_MODE") or "offline"


class ResumableTensorboardLogger(TensorboardLogger):
    """TorchRL's ``TensorboardLogger`` whose writer purges the events from ``purge_step`` on (a resume)."""

    def __init__(self, exp_name: str, log_dir: str = "tb_logs", purge_step: int | None = None) -> None:
        self.purge_step = purge_step
        super().__init__(exp_name, log_dir)

    def _create_experiment(self):
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(log_dir=os.path.join(self.log_dir, self.exp_name), purge_step=self.purge_step)


def _flat(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, Mapping):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


class MetricsLogger:
    """Log ``{name: number}`` per step to ``out_dir/metrics.csv``, wandb, TensorBoard and/or MLflow.

    In: ``out_dir`` (created); ``backends``, any of :data:`~pe_rlhf.runtime.config_rules.LOGGER_BACKENDS`:
    ``csv`` writes ``metrics.csv``; ``wandb`` starts a run (TorchRL's ``WandbLogger``, project ``project``) in the
    mode ``$WANDB_MODE`` names, ``offline`` when unset (files under ``out_dir/wandb``; ``WANDB_SILENT`` set and, unless
    online, ``WANDB_ERROR_REPORTING=false``, wandb's telemetry, so nothing touches the network unless
    ``WANDB_MODE=online``); ``tensorboard`` writes event files to ``out_dir/tensorboard`` (``TensorboardLogger``) and
    raises ``ImportError`` at construction when the ``tensorboard`` package is missing; ``mlflow`` logs to
    ``$MLFLOW_TRACKING_URI``, else to the file store ``out_dir/mlruns`` (``MLFlowLogger``, experiment ``project``;
    ``mlflow`` imported only then); ``config`` goes to wandb's run config, TensorBoard's text tab and MLflow's
    params. ``resume=True`` keeps the rows of an existing ``metrics.csv`` (and the wandb run id in
    ``out_dir/wandb_run_id``); call :meth:`truncate_after` with the checkpoint's step so that the resumed curve has
    no repeat. Without ``resume`` an existing CSV is replaced.

    Non-finite values are written as blank cells (and left out of the other loggers), with one
    ``warnings.warn`` per key. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        out_dir: str | os.PathLike,
        *,
        backends: Iterable[str] = ("csv",),
        project: str = "pe-rlhf",
        config: dict | None = None,
        resume: bool = False,
    ):
        backends = [backends] if isinstance(backends, str) else list(backends)
        if any(b not in LOGGER_BACKENDS for b in backends):
            raise ValueError(f"backends={backends!r} is invalid: allowed: any of {list(LOGGER_BACKENDS)}")
        csv, tensorboard = "csv" in backends, "tensorboard" in backends
        if tensorboard:
            self._require_tensorboard()  # before anything is written
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.config = dict(config or {})
        self.resume = bool(resume)
        self._warned: set[str] = set()
        self._closed = False
        self._tensorboard = bool(tensorboard)
        self._tb_purge_step: int | None = None
        self.loggers: dict = {}  # name -> torchrl.record.loggers.Logger, in the order they were started
        if csv:
            self.loggers["csv"] = CrashSafeCSVLogger(self.out_dir.name, self.out_dir, resume=self.resume)
        self.csv_path: Path | None = self.loggers["csv"].path if csv else None
        if "wandb" in backends:
            self.loggers["wandb"] = self._start_wandb(project)
        if "mlflow" in backends:
            self.loggers["mlflow"] = self._start_mlflow(project)

    # -- public API ------------------------------------------------------------------------------
    @property
    def columns(self) -> list[str]:
        """The CSV header, ``step`` first, then keys in order of first appearance."""
        return self.loggers["csv"].columns if "csv" in self.loggers else [STEP]

    @property
    def last_step(self) -> int | None:
        """The step of the last CSV row (None when empty)."""
        return self.loggers["csv"].last_step if "csv" in self.loggers else None

    @property
    def wandb_run(self):
        """The wandb run (``WandbLogger.experiment``), None without wandb."""
        return self.loggers["wandb"].experiment if "wandb" in self.loggers else None

    def declare(self, keys: Iterable[str]) -> None:
        """Add columns up front (one rewrite now instead of one per new key later)."""
        if "csv" in self.loggers:
            self.loggers["csv"].declare(keys)

    def log(self, step: int, metrics: Mapping[str, Any]) -> None:
        """Append one row: ``step`` and ``metrics`` (numbers; non-finite -> blank + warning)."""
        self._check_open()
        step = int(step)
        clean: dict[str, float | int | None] = {}
        for key, value in metrics.items():
            key = str(key)
            if key == STEP:
                raise ValueError(f"{STEP!r} is reserved for the step column")
            number = to_number(key, value)
            if number is None:
                raise TypeError(f"metric {key!r} must be a number, got None")
            if not math.isfinite(number):
                if key not in self._warned:
                    self._warned.add(key)
                    warnings.warn(f"metric {key!r} is not finite ({number}); written as a blank cell",
                                  RuntimeWarning, stacklevel=2)
                number = None
            clean[key] = number
        if "csv" in self.loggers:
            self.loggers["csv"].log_metrics(clean, step=step)
        finite = {k: v for k, v in clean.items() if v is not None}
        if finite:
            for name, logger in self._others():
                logger.log_metrics(finite, step=step)
                if name == "tensorboard":
                    logger.flush()

    def log_video(self, name: str, frames, step: int, fps: float = VIDEO_FPS) -> None:
        """Send ``frames`` (``(T, H, W, 3)`` uint8, a list or array) to the loggers that take videos
        (wandb, TensorBoard, MLflow; as TorchRL's ``(1, T, 3, H, W)``). A logger that cannot encode it
        (moviepy or torchcodec missing, ...) is skipped with one warning: the GIF beside the CSV stays."""
        self._check_open()
        import numpy as np
        import torch

        video = torch.from_numpy(np.ascontiguousarray(np.stack(list(frames)), dtype=np.uint8))
        video = video.permute(0, 3, 1, 2).unsqueeze(0)  # (T, H, W, C) -> (1, T, C, H, W)
        for backend, logger in self._others():
            try:
                logger.log_video(name, video, step=int(step), fps=int(round(fps)))
            except Exception as err:  # noqa: BLE001 - a video must not end a finished run
                if f"video:{backend}" not in self._warned:
                    self._warned.add(f"video:{backend}")
                    warnings.warn(f"{backend} did not take the video {name!r}: {type(err).__name__}: {err}",
                                  RuntimeWarning, stacklevel=2)

    def truncate_after(self, step: int) -> int:
        """Drop the CSV rows with ``step >= step`` (a resume from a checkpoint at ``step``).

        Returns the number of rows dropped. TensorBoard events from ``step`` on are purged when its
        writer opens; wandb steps each metric group by ``<group>/step`` and keeps what it has; MLflow
        starts a new run on every resume.
        """
        dropped = self.loggers["csv"].truncate_after(step) if "csv" in self.loggers else 0
        if self._tensorboard and "tensorboard" not in self.loggers:
            self._tb_purge_step = int(step)
        return dropped

    def close(self) -> None:
        """Close the CSV, finish the wandb and MLflow runs, close TensorBoard; idempotent."""
        self._close(exit_code=0)

    def __enter__(self) -> MetricsLogger:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._close(exit_code=0 if exc_type is None else 1)

    # -- the loggers -------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("MetricsLogger is closed")

    def _others(self):
        """The loggers besides the CSV (TensorBoard opened on first use, with the resume's purge step)."""
        if self._tensorboard and "tensorboard" not in self.loggers:
            self.loggers["tensorboard"] = self._start_tensorboard()
        return [(name, logger) for name, logger in self.loggers.items() if name != "csv"]

    def _start_wandb(self, project: str):
        os.environ.setdefault("WANDB_SILENT", "true")
        mode = wandb_mode()
        if mode != "online":
            # wandb records its own telemetry whatever the run's mode and posts it to its server from a background
            # thread (an offline run's process reached api.forge.coreweave.com); WANDB_ERROR_REPORTING=false stops
            # the recording, so an offline run sends nothing. setdefault: a user's own setting wins.
            os.environ.setdefault("WANDB_ERROR_REPORTING", "false")
        try:
            import wandb  # noqa: F401
            from torchrl.record.loggers.wandb import WandbLogger
        except Exception as err:  # noqa: BLE001 - a broken install raises more than ImportError
            raise ImportError(f"the wandb backend: wandb cannot be imported ({err}); "
                              "pip install wandb or leave wandb out of logger.backends") from err
        id_file = self.out_dir / "wandb_run_id"
        run_id = id_file.read_text().strip() if self.resume and id_file.exists() else None
        # mode goes to wandb.init: WandbLogger(offline=True) would set WANDB_MODE for the whole process
        logger = WandbLogger(self.out_dir.name, save_dir=str(self.out_dir), id=run_id, project=project,
                             log_env_packages=False, mode=mode, config=self.config)
        id_file.write_text(logger.experiment.id)
        return logger

    @staticmethod
    def _require_tensorboard() -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter  # noqa: F401
        except Exception as err:  # noqa: BLE001 - torch raises ImportError/ModuleNotFoundError
            raise ImportError(
                "the tensorboard backend needs the 'tensorboard' package, which is not installed "
                "(pip install tensorboard); log to CSV and/or wandb instead"
            ) from err

    def _start_tensorboard(self):
        logger = ResumableTensorboardLogger("tensorboard", str(self.out_dir), purge_step=self._tb_purge_step)
        if self.config:
            logger.experiment.add_text("config", "\n".join(f"{k}: {v}" for k, v in self.config.items()))
        return logger

    def _start_mlflow(self, experiment: str):
        uri = os.environ.get("MLFLOW_TRACKING_URI") or (self.out_dir / "mlruns").resolve().as_uri()
        if uri.startswith("file:"):  # MLflow 3 refuses its file store unless asked; a run folder is one
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")
        try:
            import mlflow
            from torchrl.record.loggers.mlflow import MLFlowLogger
        except Exception as err:  # noqa: BLE001
            raise ImportError(f"the mlflow backend: mlflow cannot be imported ({err}); "
                              "pip install mlflow-skinny or leave mlflow out of logger.backends") from err
        logger = MLFlowLogger(experiment, tracking_uri=uri)
        mlflow.set_tag("mlflow.runName", self.out_dir.name)
        if self.config:
            logger.log_hparams({k: str(v) for k, v in _flat(self.config).items()})
        return logger

    def _close(self, exit_code: int) -> None:
        if self._closed:
            return
        self._closed = True
        for name, logger in self.loggers.items():
            if name == "wandb":
                logger.experiment.finish(exit_code=exit_code)
            else:
                logger.shutdown()
            if name == "mlflow":  # TorchRL's shutdown leaves the run it started open
                import mlflow

                mlflow.end_run(status="FINISHED" if exit_code == 0 else "FAILED")


__all__ = ["CSV_NAME", "STEP", "MetricsLogger", "flatten_eval_summary", "read_metrics_csv", "wandb_mode"]
