"""Crash-safe journal of the batches collected since the last checkpoint (``--resume`` replays it).

A checkpoint every ``checkpoint.every_frames`` frames is too coarse for a person's time: a kill
would lose up to that many of the mentor's steps. So every collected batch is written here the
moment it arrives, before it is trained on; a resumed run loads the newest checkpoint, then replays
the journal's later batches through the same loop body (replay buffer, counters, updates,
evaluations, checkpoints), each with the RNG state the killed run had when that batch arrived, so
the resumed run's bookkeeping equals the killed run's, step for step. Files older than the newest
checkpoint are deleted after each checkpoint.

The batch being collected is covered too, up to its last finished episode: with the ``single``
backend, :class:`~pe_rlhf.runtime.episode_journal.PendingEpisodesJournal` writes a *pending* file
here each time an episode ends inside it (the batch's steps so far), deleted once the whole batch is
journaled. ``--resume`` completes the pending file that continues the journal
(:meth:`BatchJournal.pending_at`) to a whole batch with a fresh episode's steps. So a kill loses
only the steps of the episode in progress since the batch began (at most
``collector.frames_per_batch``, 10 s of driving at 10 Hz with the default 100), and that episode is
cut there. Multi-worker backends write no pending files: a kill loses
the whole batch being collected.

On disk (``directory/``), one file per batch, ``batch_{end:09d}-{sha256[:16]}.pt``, and pending
files ``pending_{start:09d}_{end:09d}-{sha256[:16]}.pt`` (frames ``[start, end)`` of the batch that
starts at ``start``): ``torch.save`` of ``{"format_version", "start", "end", "batch_size", "batch":
batch.to_dict(), "rng": capture_rng(), "state": JSON text}`` (plain tensors, ints, lists and
strings: loaded with ``weights_only=True``), written to a temp file, fsync'd and renamed (a file
exists whole or not at all); the name carries the first 16 hex digits of the file's sha256, checked
on reading.
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

from pe_rlhf import durable
from pe_rlhf.runtime.checkpoint import CheckpointError, capture_rng, short_error

__all__ = ["BatchJournal", "JournalEntry"]

FORMAT_VERSION = 1
ENTRY_NAME = re.compile(r"^batch_(\d{9,})-([0-9a-f]{16})\.pt$")
PENDING_NAME = re.compile(r"^pending_(\d{9,})_(\d{9,})-([0-9a-f]{16})\.pt$")


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
    """Write, list, read and prune the batch and pending files under ``directory`` (see the module docstring)."""

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def write(self, batch: TensorDictBase, start: int, state: dict[str, Any] | None = None) -> Path:
        """Journal ``batch`` (frames ``[start, start + batch.numel())``) with the current RNG state and
        ``state`` (JSON-serialisable: transform step count, mentor state). Raises ``OSError`` (disk
        full, ...) naming the file; a failed write leaves no file behind."""
        end = int(start) + int(batch.numel())
        return self._write(lambda sha: f"batch_{end:09d}-{sha}.pt", batch, start, state)

    def write_pending(self, batch: TensorDictBase, start: int, state: dict[str, Any] | None = None) -> Path:
        """Write the first ``batch.numel()`` steps of the batch starting at frame ``start`` (up to an
        episode's end) as a pending file, then delete the shorter pending files of that batch. Errors as
        :meth:`write`."""
        end = int(start) + int(batch.numel())
        path = self._write(lambda sha: f"pending_{int(start):09d}_{end:09d}-{sha}.pt", batch, start, state)
        for other_start, other_end, other in self.pending_files():
            if other_start == int(start) and other_end < end:
                other.unlink(missing_ok=True)
        return path

    def _write(self, name, batch: TensorDictBase, start: int, state: dict[str, Any] | None) -> Path:
        end = int(start) + int(batch.numel())
        payload = {"format_version": FORMAT_VERSION, "start": int(start), "end": end,
                   "batch_size": list(batch.batch_size), "batch": batch.to_dict(), "rng": capture_rng(),
                   "state": json.dumps(state or {})}
        buf = io.BytesIO()
        torch.save(payload, buf)
        data = buf.getvalue()
        path = self.directory / name(hashlib.sha256(data).hexdigest()[:16])
        try:
            durable.replace_bytes(path, data)
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

    def pending_files(self) -> list[tuple[int, int, Path]]:
        """``(start, end, path)`` of every pending file, oldest first."""
        found = []
        for path in self.directory.iterdir():
            m = PENDING_NAME.match(path.name)
            if m and path.is_file():
                found.append((int(m.group(1)), int(m.group(2)), path))
        return sorted(found)

    def read(self, path: Path) -> JournalEntry:
        """One entry (batch or pending file); :class:`~pe_rlhf.runtime.checkpoint.CheckpointError`
        naming the file if it is corrupt, truncated, unsafe (refused by ``weights_only=True``) or malformed."""
        m = ENTRY_NAME.match(path.name) or PENDING_NAME.match(path.name)
        data = path.read_bytes()
        if m is None or hashlib.sha256(data).hexdigest()[:16] != m.groups()[-1]:
            raise CheckpointError(f"journal file {path} is corrupt or truncated: its sha256 does not match its name")
        try:
            p = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
            if p["format_version"] != FORMAT_VERSION:
                raise ValueError(f"format_version {p['format_version']!r}; this pe_rlhf reads {FORMAT_VERSION}")
            batch = TensorDict(p["batch"], batch_size=p["batch_size"])
            state = json.loads(p["state"])
            start, end = int(p["start"]), int(p["end"])
            named = [int(frame) for frame in m.groups()[:-1]]
            if named != ([end] if m.re is ENTRY_NAME else [start, end]) or end - start != batch.numel():
                raise ValueError(f"frames {start}-{end} do not match the name or the batch's {batch.numel()} steps")
        except Exception as e:  # noqa: BLE001 - unpickling/shape errors of every kind: name the file, no stack
            raise CheckpointError(f"unreadable journal file {path}: {short_error(e)}") from None
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

    def pending_at(self, frame: int) -> JournalEntry | None:
        """The pending file that continues the journal at ``frame`` (the longest readable one), or None.
        Every other pending file is deleted: older ones are journaled already, later ones cannot
        continue it. An unreadable one is deleted with a warning naming it."""
        found = None
        for start, _, path in sorted(self.pending_files(), key=lambda f: (f[0] != frame, -f[1])):
            if start == frame and found is None:
                try:
                    found = self.read(path)
                    continue
                except CheckpointError as e:
                    warnings.warn(f"{e}; the steps it held are lost", stacklevel=2)
            path.unlink(missing_ok=True)
        return found

    def discard_pending(self, start: int) -> None:
        """Delete the pending files of batches starting at or before frame ``start`` (journaled now)."""
        for first, _, path in self.pending_files():
            if first <= start:
                path.unlink(missing_ok=True)

    def prune(self, frame: int) -> None:
        """Delete the files of frames up to ``frame`` (a checkpoint holds them now), and any leftover
        temp files of a killed writer."""
        for end, path in self.files():
            if end <= frame:
                path.unlink(missing_ok=True)
        for pattern in (".batch_*.tmp-*", ".pending_*.tmp-*"):
            for path in self.directory.glob(pattern):
                path.unlink(missing_ok=True)
