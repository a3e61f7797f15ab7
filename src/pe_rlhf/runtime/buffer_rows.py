"""The rows a learner's replay buffers hold: non-finite rows dropped on ``--resume``, checkpoints of filled rows only,
and the memory a buffer's capacity will take, estimated before a run starts.

A learner's buffer is a TorchRL ``ReplayBuffer`` over a ``TensorStorage``, or a composite whose attributes are such
buffers (the proxy-Q learner's takeover-balanced buffer): :func:`torchrl_buffers` finds them.

- :func:`drop_non_finite_rows`: a row with a NaN or inf anywhere (an observation that reached the buffer before the
  env checked its resets) would stop every update again; ``--resume`` keeps the others, in their order.
- :func:`filled_rows_only`: while a checkpoint is written or read, each storage saves and loads its first ``len``
  rows only (:class:`FilledRowsCheckpointer`), each tensor file zlib-compressed (``*.memmap.zlib``: raw bytes, never
  unpickled), so a checkpoint is the size of what was collected, not of the capacity (whose unused rows are
  uninitialised memory). A checkpoint written whole and raw (before this) loads too.
- :func:`check_buffer_fits`: a capacity whose rows cannot fit in this machine's memory is refused (ConfigError
  naming the field and the estimate) before anything is written.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data import ReplayBuffer
from torchrl.data.replay_buffers.checkpointers import TensorStorageCheckpointer
from torchrl.data.replay_buffers.storages import TensorStorage

from pe_rlhf.runtime.config_rules import ConfigError

MEMMAP, ZLIB = ".memmap", ".zlib"  # a buffer's tensor files, and the compressed ones a checkpoint holds

__all__ = ["FilledRowsCheckpointer", "check_buffer_fits", "drop_non_finite_rows", "filled_rows_only",
           "torchrl_buffers"]


def torchrl_buffers(buffer) -> list[ReplayBuffer]:
    """``buffer`` itself when it is a TorchRL replay buffer, else the TorchRL buffers among its attributes."""
    if isinstance(buffer, ReplayBuffer):
        return [buffer]
    return [v for v in vars(buffer).values() if isinstance(v, ReplayBuffer)]


def _finite_rows(rows) -> torch.Tensor:
    """``(N,)`` bool: the rows of ``rows`` whose every floating leaf is finite."""
    keep = torch.ones(rows.shape[0], dtype=torch.bool)
    for _, value in rows.items(include_nested=True, leaves_only=True):
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            keep &= torch.isfinite(value.reshape(value.shape[0], -1)).all(-1)
    return keep


def drop_non_finite_rows(buffer) -> int:
    """Remove the rows holding a NaN or inf from ``buffer`` (kept rows in their order); returns how many went."""
    dropped = 0
    for rb in torchrl_buffers(buffer):
        if len(rb) == 0:
            continue
        rows = rb[:]
        keep = _finite_rows(rows)
        if bool(keep.all()):
            continue
        dropped += int((~keep).sum())
        kept = rows[keep].clone()
        rb.empty()
        if kept.shape[0]:
            rb.extend(kept)
    return dropped


class FilledRowsCheckpointer(TensorStorageCheckpointer):
    """TorchRL's ``TensorStorageCheckpointer`` for the filled rows only: ``dumps`` writes ``storage[:len]``,
    ``loads`` reads however many rows the folder holds into the first rows of the storage (its capacity kept)."""

    def dumps(self, storage, path):
        full = storage._storage
        storage._storage = full[: len(storage)]
        try:
            super().dumps(storage, path)
        finally:
            storage._storage = full
        for raw in Path(path).rglob(f"*{MEMMAP}"):  # observations compress about tenfold (lidar beams at range)
            (raw.parent / (raw.name + ZLIB)).write_bytes(zlib.compress(raw.read_bytes(), 1))
            raw.unlink()

    def loads(self, storage, path):
        path = Path(path)
        with tempfile.TemporaryDirectory(prefix="pe_rlhf-buffer-") as tmp:
            if any(path.rglob(f"*{MEMMAP}{ZLIB}")):  # decompressed beside, never in the checkpoint
                for src in path.rglob("*"):
                    dst = Path(tmp) / src.relative_to(path)
                    if src.is_dir():
                        dst.mkdir(parents=True, exist_ok=True)
                    elif src.name.endswith(ZLIB):
                        dst.parent.mkdir(parents=True, exist_ok=True)
                        dst.with_name(dst.name[: -len(ZLIB)]).write_bytes(zlib.decompress(src.read_bytes()))
                    else:
                        dst.parent.mkdir(parents=True, exist_ok=True)
                        shutil.copyfile(src, dst)
                source = Path(tmp)
            else:  # a checkpoint written before: raw memmaps, possibly of the whole capacity
                source = path
            rows = TensorDict.load_memmap(source)
            length = int(json.loads((source / "storage_metadata.json").read_text())["len"])
            if length > storage.max_size or rows.shape[0] < length:
                raise ValueError(f"{path} holds {length} rows; the buffer's capacity is {storage.max_size} "
                                 "(replay_buffer.size must be at least what the checkpoint holds)")
            if not storage.initialized:
                storage._init(rows[0])
            storage._storage[:length].update_(rows[:length])
            storage._len = length
            del rows  # the memmaps close before their folder goes


@contextlib.contextmanager
def filled_rows_only(buffer) -> Iterator[None]:
    """Inside: every TensorStorage of ``buffer`` checkpoints its filled rows only (:class:`FilledRowsCheckpointer`)."""
    storages = [rb._storage for rb in torchrl_buffers(buffer) if isinstance(rb._storage, TensorStorage)]
    saved = [s.checkpointer for s in storages]
    for s in storages:
        s.checkpointer = FilledRowsCheckpointer()
    try:
        yield
    finally:
        for s, checkpointer in zip(storages, saved):
            s.checkpointer = checkpointer


def memory_bytes() -> int | None:
    """This machine's physical memory in bytes (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_buffer_fits(field: str, rows: int, row_bytes: int, copies: int = 1, *, saved_rows: int | None = None,
                      checkpoints: int = 2, folder: str | os.PathLike | None = None) -> None:
    """ConfigError naming ``field`` and the estimate when ``copies`` storages of ``rows`` rows of ``row_bytes`` each
    cannot fit in this machine's memory (a storage is allocated whole when its first row arrives), or when
    ``checkpoints`` checkpoints of ``saved_rows`` rows each (at most ``rows``; compression not counted) cannot fit
    on the disk that holds ``folder`` (its nearest existing parent)."""
    need, have = int(rows) * int(row_bytes) * int(copies), memory_bytes()
    if have is not None and need > have:
        raise ConfigError(f"{field}={rows} is invalid: its {copies} buffer storage(s) of {rows} rows would take about "
                          f"{need / 1e9:.1f} GB ({row_bytes} bytes a row), more than this machine's "
                          f"{have / 1e9:.1f} GB of memory; use a smaller {field}", field)
    if folder is None or saved_rows is None:
        return
    existing = Path(folder).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    disk = int(min(int(rows), int(saved_rows)) * int(row_bytes) * int(checkpoints))
    free = shutil.disk_usage(existing).free
    if disk > free:
        raise ConfigError(f"{field}={rows} is invalid: {checkpoints} checkpoints of up to {min(rows, saved_rows)} rows "
                          f"would take about {disk / 1e9:.1f} GB, more than the {free / 1e9:.1f} GB free under "
                          f"{existing}; use a smaller {field} or another --out", field)
