"""Training metrics to a crash-safe CSV, and optionally to wandb (offline) and TensorBoard.

One row per :meth:`MetricsLogger.log` call: ``step`` (environment steps) plus the
given metrics. Column names follow the convention in :mod:`pe_rlhf.training.plots`
(``train/...``, ``loss/...``, ``eval/<metric>_mean`` / ``eval/<metric>_std``);
:func:`flatten_eval_summary` turns an evaluation summary into the ``eval/`` columns.

The CSV is readable at every moment: a row is appended, flushed and fsync'ed per
call; when new columns appear the whole file is rewritten to a temporary file and
atomically swapped in (:func:`os.replace`), so a crash leaves either the old or
the new file, never half of one. Rows logged at the same step by separate calls
(e.g. training, then evaluation) stay separate rows; readers drop blank cells.
"""

from __future__ import annotations

import csv
import math
import numbers
import os
import tempfile
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

STEP = "step"
CSV_NAME = "metrics.csv"


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


def _to_number(key: str, value: Any) -> float | int:
    if hasattr(value, "item") and callable(value.item):  # torch / numpy scalars
        value = value.item()
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    raise TypeError(f"metric {key!r} must be a number, got {type(value).__name__}")


def _cell(value: float | int | None) -> str:
    if value is None:
        return ""
    return str(value) if isinstance(value, int) else repr(float(value))


class MetricsLogger:
    """Log ``{name: number}`` per step to ``out_dir/metrics.csv``, wandb and/or TensorBoard.

    In: ``out_dir`` (created); ``csv`` writes ``metrics.csv``; ``wandb`` starts a run
    (imported lazily; ``mode="offline"`` by default, files under ``out_dir/wandb``,
    ``WANDB_SILENT`` set, so nothing touches the network unless ``wandb_mode="online"``);
    ``tensorboard`` writes event files to ``out_dir/tensorboard`` and raises
    ``ImportError`` at construction when the ``tensorboard`` package is missing;
    ``config`` goes to wandb's run config and TensorBoard's text tab.
    ``resume=True`` keeps the rows of an existing ``metrics.csv`` (and the wandb run id
    in ``out_dir/wandb_run_id``); call :meth:`truncate_after` with the checkpoint's step
    so that the resumed curve has no repeat. Without ``resume`` an existing CSV is replaced.

    Non-finite values are written as blank cells (and left out of wandb/TensorBoard),
    with one ``warnings.warn`` per key. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        out_dir: str | os.PathLike,
        *,
        csv: bool = True,
        wandb: bool = False,
        wandb_mode: str = "offline",
        wandb_project: str = "pe-rlhf",
        tensorboard: bool = False,
        config: dict | None = None,
        resume: bool = False,
    ):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.config = dict(config or {})
        self.resume = bool(resume)
        self._warned: set[str] = set()
        self._closed = False
        self._columns: list[str] = [STEP]
        self._rows: list[dict[str, str]] = []
        self._file = None
        self._writer = None
        self._tb_module = self._import_tensorboard() if tensorboard else None
        self._tb = None
        self._tb_purge_step: int | None = None
        self.wandb_run = None

        self.csv_path: Path | None = self.out_dir / CSV_NAME if csv else None
        if self.csv_path is not None:
            if self.resume and self.csv_path.exists():
                self._load_existing()
            self._rewrite()
        if wandb:
            self.wandb_run = self._start_wandb(wandb_mode, wandb_project)

    # -- public API ------------------------------------------------------------------------------
    @property
    def columns(self) -> list[str]:
        """The CSV header, ``step`` first, then keys in order of first appearance."""
        return list(self._columns)

    @property
    def last_step(self) -> int | None:
        """The step of the last CSV row (None when empty)."""
        for row in reversed(self._rows):
            if row.get(STEP, "") != "":
                return int(float(row[STEP]))
        return None

    def declare(self, keys: Iterable[str]) -> None:
        """Add columns up front (one rewrite now instead of one per new key later)."""
        new = [k for k in keys if k not in self._columns]
        if new:
            self._columns.extend(new)
            if self.csv_path is not None:
                self._rewrite()

    def log(self, step: int, metrics: Mapping[str, Any]) -> None:
        """Append one row: ``step`` and ``metrics`` (numbers; non-finite -> blank + warning)."""
        self._check_open()
        step = int(step)
        clean: dict[str, float | int | None] = {}
        for key, value in metrics.items():
            key = str(key)
            if key == STEP:
                raise ValueError(f"{STEP!r} is reserved for the step column")
            number = _to_number(key, value)
            if not math.isfinite(number):
                if key not in self._warned:
                    self._warned.add(key)
                    warnings.warn(f"metric {key!r} is not finite ({number}); written as a blank cell",
                                  RuntimeWarning, stacklevel=2)
                number = None
            clean[key] = number
        if self.csv_path is not None:
            self._append_csv(step, clean)
        finite = {k: v for k, v in clean.items() if v is not None}
        if self.wandb_run is not None and finite:
            self.wandb_run.log(finite, step=step)
        if self._tb_module is not None and finite:
            tb = self._tensorboard()
            for key, value in finite.items():
                tb.add_scalar(key, value, global_step=step)
            tb.flush()

    def truncate_after(self, step: int) -> int:
        """Drop the CSV rows with ``step >= step`` (a resume from a checkpoint at ``step``).

        Returns the number of rows dropped. TensorBoard events from ``step`` on are purged
        when its writer opens; wandb ignores steps below its last one (offline runs keep them).
        """
        step = int(step)
        kept = [r for r in self._rows if r.get(STEP, "") == "" or int(float(r[STEP])) < step]
        dropped = len(self._rows) - len(kept)
        self._rows = kept
        if self.csv_path is not None:
            self._rewrite()
        if self._tb_module is not None and self._tb is None:
            self._tb_purge_step = step
        return dropped

    def close(self) -> None:
        """Close the CSV, finish the wandb run, close TensorBoard; idempotent."""
        self._close(exit_code=0)

    def __enter__(self) -> MetricsLogger:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._close(exit_code=0 if exc_type is None else 1)

    # -- CSV ---------------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("MetricsLogger is closed")

    def _load_existing(self) -> None:
        with open(self.csv_path, newline="") as f:
            reader = csv.DictReader(f)
            header = [c for c in (reader.fieldnames or []) if c]
            rows = [{k: v for k, v in r.items() if k and v not in (None, "")} for r in reader]
        self._columns = [STEP] + [c for c in header if c != STEP]
        self._rows = rows

    def _append_csv(self, step: int, clean: Mapping[str, float | int | None]) -> None:
        row = {STEP: str(step)}
        row.update({k: _cell(v) for k, v in clean.items()})
        self._rows.append(row)
        new = [k for k in clean if k not in self._columns]
        if new:
            self._columns.extend(new)
            self._rewrite()
            return
        self._writer.writerow(row)
        self._sync()

    def _rewrite(self) -> None:
        """Write header + all rows to a temp file, fsync, swap it in, reopen for appending."""
        if self._file is not None:
            self._file.close()
            self._file = None
        fd, tmp = tempfile.mkstemp(prefix=".metrics-", suffix=".csv.tmp", dir=self.out_dir)
        try:
            with os.fdopen(fd, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=self._columns, restval="", extrasaction="ignore")
                writer.writeheader()
                writer.writerows(self._rows)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.csv_path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        self._fsync_dir()
        self._file = open(self.csv_path, "a", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=self._columns, restval="",
                                      extrasaction="ignore")

    def _sync(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())

    def _fsync_dir(self) -> None:
        try:
            fd = os.open(self.out_dir, os.O_RDONLY)
        except OSError:  # e.g. Windows: directories cannot be opened
            return
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)

    # -- wandb / TensorBoard -----------------------------------------------------------------------
    def _start_wandb(self, mode: str, project: str):
        os.environ.setdefault("WANDB_SILENT", "true")
        try:
            import wandb
        except Exception as err:  # noqa: BLE001 - a broken install raises more than ImportError
            raise ImportError(f"wandb=True but wandb cannot be imported ({err}); "
                              "pip install wandb or pass wandb=False") from err
        id_file = self.out_dir / "wandb_run_id"
        run_id = id_file.read_text().strip() if self.resume and id_file.exists() else None
        run = wandb.init(project=project, dir=str(self.out_dir), mode=mode, config=self.config,
                         id=run_id, resume="allow" if run_id else None)
        id_file.write_text(run.id)
        return run

    @staticmethod
    def _import_tensorboard():
        try:
            from torch.utils.tensorboard import SummaryWriter
        except Exception as err:  # noqa: BLE001 - torch raises ImportError/ModuleNotFoundError
            raise ImportError(
                "tensorboard=True needs the 'tensorboard' package, which is not installed "
                "(pip install tensorboard); log to CSV and/or wandb instead"
            ) from err
        return SummaryWriter

    def _tensorboard(self):
        if self._tb is None:
            self._tb = self._tb_module(log_dir=str(self.out_dir / "tensorboard"),
                                       purge_step=self._tb_purge_step)
            if self.config:
                self._tb.add_text("config", "\n".join(f"{k}: {v}" for k, v in self.config.items()))
        return self._tb

    def _close(self, exit_code: int) -> None:
        if self._closed:
            return
        self._closed = True
        if self._file is not None:
            self._sync()
            self._file.close()
            self._file = None
        if self.wandb_run is not None:
            self.wandb_run.finish(exit_code=exit_code)
        if self._tb is not None:
            self._tb.close()
