"""Crash-safe journal of the batches collected since the last checkpoint (``--resume`` replays it).

A checkpoint every ``checkpoint.every_frames`` frames is too coarse for a person's time: a kill
would lose up to that many of the mentor's steps. So every collected batch is written here the
moment it arrives, before it is trained on; a resumed run loads the newest checkpoint, then replays
the journal's later batches through the same loop body (replay buffer, counters, updates,
evaluations, checkpoints), each with the RNG state the killed run had when that batch arrived, so
the resumed run's bookkeeping equals the killed run's, step for step. A kill loses only the batch
being collected (at most ``collector.frames_per_batch`` steps, 10 s of driving at 10 Hz with the
default 100) and the episode in progress is cut there. Files older than the newest checkpoint are
deleted after each checkpoint.

On disk (``directory/``), one file per batch, ``batch_{end:09d}-{sha256[:16]}.pt``: ``torch.save``
of ``{"format_version", "start", "end", "batch_size", "batch": batch.to_dict(), "rng":
capture_rng(), "state": JSON text}`` (plain tensors, ints, lists and strings: loaded with
``weights_only=True``), written to a temp file, fsync'd and renamed (a file exists whole or not at
all); the name carries the first 16 hex digits of the file's sha256, checked on reading.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from pe_rlhf.training.checkpoint import CheckpointError, _atomic_write, _short, capture_rng

__all__ = ["BatchJournal", "JournalEntry"]

FORMAT_VERSION = 1
ENTRY_NAME = re.compile(r"^batch_(\d{9,})-([0-9a-f]{16})\.pt$")


@dataclass
class JournalEntry:
    """One journaled batch: frames ``[start, end)`` of the run, as collected."""

    path: Path
    start: int
    end: int
    batch: TensorDictBase
    rng: dict[str, Any]
    state: dict[str, Any]


class BatchJournal:
    """Write, list, read and prune the batch files under ``directory`` (see the module docstring)."""

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def write(self, batch: TensorDictBase, start: int, state: dict[str, Any] | None = None) -> Path:
        """Journal ``batch`` (frames ``[start, start + batch.numel())``) with the current RNG state and
        ``state`` (JSON-serialisable: transform step count, mentor state). Raises ``OSError`` (disk
        full, ...) naming the file; a failed write leaves no file behind."""
        end = int(start) + int(batch.numel())
        payload = {"format_version": FORMAT_VERSION, "start": int(start), "end": end,
                   "batch_size": list(batch.batch_size), "batch": batch.to_dict(), "rng": capture_rng(),
                   "state": json.dumps(state or {})}
        buf = io.BytesIO()
        torch.save(payload, buf)
        data = buf.getvalue()
        path = self.directory / f"batch_{end:09d}-{hashlib.sha256(data).hexdigest()[:16]}.pt"
        try:
            _atomic_write(path, data)
        except OSError as e:
            raise OSError(e.errno, f"could not journal frames {start}-{end} to {path}: "
                                   f"{e.strerror or e}") from e
        return path

    def files(self) -> list[tuple[int, Path]]:
        """``(end frame, path)`` of every journal file, oldest first (temp files and strangers skipped)."""
        found = []
        for path in self.directory.iterdir():
            m = ENTRY_NAME.match(path.name)
            if m and path.is_file():
                found.append((int(m.group(1)), path))
        return sorted(found)

    def read(self, path: Path) -> JournalEntry:
        """One entry; :class:`~pe_rlhf.training.checkpoint.CheckpointError` naming the file if it is
        corrupt, truncated, unsafe (refused by ``weights_only=True``) or malformed."""
        m = ENTRY_NAME.match(path.name)
        data = path.read_bytes()
        if m is None or hashlib.sha256(data).hexdigest()[:16] != m.group(2):
            raise CheckpointError(f"journal file {path} is corrupt or truncated: its sha256 does not match its name")
        try:
            p = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
            if p["format_version"] != FORMAT_VERSION:
                raise ValueError(f"format_version {p['format_version']!r}; this pe_rlhf reads {FORMAT_VERSION}")
            batch = TensorDict(p["batch"], batch_size=p["batch_size"])
            state = json.loads(p["state"])
            start, end = int(p["start"]), int(p["end"])
            if end != int(m.group(1)) or end - start != batch.numel():
                raise ValueError(f"frames {start}-{end} do not match the name or the batch's {batch.numel()} steps")
        except Exception as e:  # noqa: BLE001 - unpickling/shape errors of every kind: name the file, no stack
            raise CheckpointError(f"unreadable journal file {path}: {_short(e)}") from None
        return JournalEntry(path, start, end, batch, p["rng"], state)

    def entries_after(self, frame: int) -> list[JournalEntry]:
        """The entries that continue a checkpoint at ``frame``: contiguous, oldest first. Replay stops
        (with a warning naming the file) at the first unreadable file or gap; that file and every later
        one are deleted, since the resumed run collects those frames anew."""
        entries, expected = [], int(frame)
        later = [(end, path) for end, path in self.files() if end > frame]
        for i, (_, path) in enumerate(later):
            try:
                entry = self.read(path)
                if entry.start != expected:
                    raise CheckpointError(f"journal file {path} starts at frame {entry.start}, expected {expected}")
            except CheckpointError as e:
                warnings.warn(f"{e}; replaying the journal up to frame {expected} only", stacklevel=2)
                for _, stale in later[i:]:
                    stale.unlink(missing_ok=True)
                break
            entries.append(entry)
            expected = entry.end
        return entries

    def prune(self, frame: int) -> None:
        """Delete the files of frames up to ``frame`` (a checkpoint holds them now), and any leftover
        temp files of a killed writer."""
        for end, path in self.files():
            if end <= frame:
                path.unlink(missing_ok=True)
        for path in self.directory.glob(".batch_*.tmp-*"):
            path.unlink(missing_ok=True)
