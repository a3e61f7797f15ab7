"""The crash-safe metrics CSV as a TorchRL ``Logger`` (``torchrl.record.loggers``).

:class:`CrashSafeCSVLogger` writes ``<log_dir>/metrics.csv``: a header ``step, <metric>...`` (keys in
order of first appearance) and one row per :meth:`~CrashSafeCSVLogger.log_metrics` call (a
``log_scalar`` call is a row of one metric). Rows logged at the same step by separate calls (training,
then evaluation) stay separate rows; a metric a row does not hold, or a non-finite value, is a blank
cell, and readers drop blank cells.

The file is readable at every moment: a row is appended, flushed and fsync'ed per call; when new columns
appear the whole file is rewritten to a temporary file and atomically swapped in (:func:`os.replace`),
so a crash leaves either the old or the new file, never half of one. ``resume=True`` keeps the rows of an
existing file and :meth:`~CrashSafeCSVLogger.truncate_after` drops those from a checkpoint's step on, so
a resumed curve has no repeat; without ``resume`` an existing file is replaced.
"""

from __future__ import annotations

import csv
import io
import math
import numbers
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from torchrl.record.loggers.common import Logger, _make_metrics_safe

from pe_rlhf import durable

STEP = "step"
CSV_NAME = "metrics.csv"


def to_number(key: str, value: Any) -> float | int | None:
    """A metric value as a Python number (torch/numpy scalars, bools as 0/1); None stays None (a blank cell)."""
    if value is None:
        return None
    if hasattr(value, "item") and callable(value.item):  # torch / numpy scalars
        value = value.item()
    if isinstance(value, numbers.Integral):  # bool included
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    raise TypeError(f"metric {key!r} must be a number, got {type(value).__name__}")


def _cell(value: float | int | None) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return str(value) if isinstance(value, int) else repr(float(value))


class CrashSafeCSV:
    """The file behind :class:`CrashSafeCSVLogger` (its ``experiment``): header, rows, fsync'd appends,
    atomic rewrites. Rows are kept in memory as the strings written."""

    def __init__(self, path: str | os.PathLike, resume: bool = False):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.columns: list[str] = [STEP]
        self.rows: list[dict[str, str]] = []
        self._file = None
        self._writer = None
        self.closed = False
        if resume and self.path.exists():
            self._load_existing()
        self._rewrite()

    @property
    def last_step(self) -> int | None:
        """The step of the last row that has one (None when there is none)."""
        for row in reversed(self.rows):
            if row.get(STEP, "") != "":
                return int(float(row[STEP]))
        return None

    def append(self, step: int | None, values: Mapping[str, float | int | None]) -> None:
        """One row: ``step`` (None: blank) and ``values``; new keys become columns (a rewrite)."""
        if self.closed:
            raise RuntimeError(f"{self.path} is closed")
        row = {STEP: "" if step is None else str(int(step))}
        row.update({k: _cell(v) for k, v in values.items()})
        self.rows.append(row)
        new = [k for k in values if k not in self.columns]
        if new:
            self.columns.extend(new)
            self._rewrite()
            return
        self._writer.writerow(row)
        self.flush()

    def declare(self, keys: Iterable[str]) -> None:
        """Add columns up front (one rewrite now instead of one per new key later)."""
        new = [k for k in keys if k not in self.columns]
        if new:
            self.columns.extend(new)
            self._rewrite()

    def truncate_after(self, step: int) -> int:
        """Drop the rows with ``step >= step``; returns how many were dropped."""
        step = int(step)
        kept = [r for r in self.rows if r.get(STEP, "") == "" or int(float(r[STEP])) < step]
        dropped = len(self.rows) - len(kept)
        self.rows = kept
        self._rewrite()
        return dropped

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()
            os.fsync(self._file.fileno())

    def close(self) -> None:
        """Flush and close the file; idempotent."""
        if self._file is not None:
            self.flush()
            self._file.close()
            self._file = None
        self.closed = True

    def _load_existing(self) -> None:
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            header = [c for c in (reader.fieldnames or []) if c]
            rows = [{k: v for k, v in r.items() if k and v not in (None, "")} for r in reader]
        self.columns = [STEP] + [c for c in header if c != STEP]
        self.rows = rows

    def _rewrite(self) -> None:
        """Write header + all rows atomically (:func:`pe_rlhf.durable.replace_bytes`), reopen for appending."""
        if self._file is not None:
            self._file.close()
            self._file = None
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, fieldnames=self.columns, restval="", extrasaction="ignore")
        writer.writeheader()
        writer.writerows(self.rows)
        durable.replace_bytes(self.path, text.getvalue().encode())  # temp file, fsync, rename, directory fsync
        self._file = open(self.path, "a", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=self.columns, restval="", extrasaction="ignore")


class CrashSafeCSVLogger(Logger):
    """TorchRL ``Logger`` over one crash-safe CSV, ``<log_dir>/<file_name>`` (see the module docstring).

    ``log_metrics(metrics, step)`` writes one row; ``log_scalar(name, value, step)`` a row of one value.
    Videos, hyper-parameters and histograms are not written: a CSV holds scalars (the recipes save
    ``config.yaml`` and the test-episode GIF beside it); ``log_video``/``log_hparams`` do nothing and
    ``log_histogram`` raises ``NotImplementedError``. ``shutdown()`` (alias ``close()``, or leaving a
    ``with`` block) closes the file.
    """

    def __init__(self, exp_name: str, log_dir: str | os.PathLike, *, resume: bool = False,
                 file_name: str = CSV_NAME) -> None:
        self.path = Path(log_dir) / file_name
        self.resume = bool(resume)
        super().__init__(exp_name=exp_name, log_dir=str(log_dir))

    def _create_experiment(self) -> CrashSafeCSV:
        return CrashSafeCSV(self.path, resume=self.resume)

    @property
    def columns(self) -> list[str]:
        """The header, ``step`` first, then keys in order of first appearance."""
        return list(self.experiment.columns)

    @property
    def last_step(self) -> int | None:
        return self.experiment.last_step

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        self.log_metrics({name: value}, step=step)

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None, *,
                    keys_sep: str = "/") -> dict[str, Any]:
        """One row: ``step`` (None: blank) and ``metrics`` (a dict or TensorDict; None or non-finite: blank)."""
        if STEP in metrics:
            raise ValueError(f"{STEP!r} is reserved for the step column")
        values = {str(k): to_number(str(k), v) for k, v in _make_metrics_safe(metrics, keys_sep=keys_sep).items()}
        self.experiment.append(step, values)
        return values

    def declare(self, keys: Iterable[str]) -> None:
        """Columns up front (see :meth:`CrashSafeCSV.declare`)."""
        self.experiment.declare(keys)

    def truncate_after(self, step: int) -> int:
        """Drop the rows with ``step >= step`` (a resume from a checkpoint at ``step``); returns how many."""
        return self.experiment.truncate_after(step)

    def log_video(self, name: str, video, step: int | None = None, **kwargs) -> None:
        """Nothing: a CSV holds scalars."""

    def log_hparams(self, cfg) -> None:
        """Nothing: a CSV holds scalars (the recipes save ``config.yaml`` beside it)."""

    def log_histogram(self, name: str, data: Sequence, **kwargs):
        raise NotImplementedError("CrashSafeCSVLogger holds scalars only")

    def __enter__(self) -> CrashSafeCSVLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()

    def __repr__(self) -> str:
        return f"CrashSafeCSVLogger(path={str(self.path)!r}, rows={len(self.experiment.rows)})"


__all__ = ["CSV_NAME", "STEP", "CrashSafeCSV", "CrashSafeCSVLogger", "to_number"]
