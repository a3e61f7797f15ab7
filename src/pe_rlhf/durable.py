"""Durable file writes, the same on POSIX and Windows: every byte written, fsync'd, renamed atomically.

One place for what checkpoints, human-demonstration recordings, the crash-safe CSV and reports need:

- :func:`write_bytes` writes a whole buffer (``os.write`` may write less than asked) and fsyncs it;
  ``append=True`` appends (one small ``O_APPEND`` write is not torn by a process kill).
- :func:`replace_bytes` writes a temp file beside ``path``, fsyncs it, renames it over ``path`` and
  fsyncs the directory: readers see the old file or the new one, never a part.
- :func:`fsync_path` makes a written file's data, or a directory's entries, durable.
- :func:`sha256_file` hashes a file in chunks.
- :func:`save_tensors` / :func:`load_tensors`: weights (an actor, critics, the packaged expert) as a safetensors
  file (plain tensors and a string table: nothing in it can run code), written with :func:`replace_bytes`; a legacy
  torch file (``.pt``) loads with ``weights_only=True``. A truncated, corrupt or unsafe file of either kind is a
  ``ValueError`` in one line naming the file and what is wrong.

Windows: files are opened in binary mode (``O_BINARY``; without it, ``os.write`` translates
newlines); a file's fsync needs a writable handle, so it is reopened read-write; directories cannot
be opened there, and NTFS journals renames itself, so a directory fsync is a no-op.

Why written here rather than taken from a library: the one package for it, ``atomicwrites``, was archived by its
author (last release 1.4.1, July 2022), and it offers no torn-free
``O_APPEND`` journal line as the crash-safe CSV and the recorder's manifest need. The whole of it is the ~60
lines below, each exercised by ``tests/test_durable.py`` and ``tests/reliability/``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
from pathlib import Path

_BINARY = getattr(os, "O_BINARY", 0)  # 0 on POSIX
_WINDOWS = os.name == "nt"
_HASH_CHUNK = 1 << 20


def write_bytes(path: str | os.PathLike, data: bytes, *, append: bool = False) -> None:
    """Write all of ``data`` to ``path`` (created; truncated unless ``append``), then fsync it."""
    mode = os.O_APPEND if append else os.O_TRUNC
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | mode | _BINARY, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_path(path: str | os.PathLike) -> None:
    """fsync an existing file, or a directory's entries (a no-op for directories on Windows)."""
    path = Path(path)
    if path.is_dir():
        if _WINDOWS:
            return
        flags = os.O_RDONLY
    else:
        flags = (os.O_RDWR if _WINDOWS else os.O_RDONLY) | _BINARY
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_bytes(path: str | os.PathLike, data: bytes, *, tmp: str | os.PathLike | None = None) -> Path:
    """Atomically replace ``path``'s content with ``data`` (temp file, fsync, rename, directory fsync).

    ``tmp``: the temp file's path (beside ``path``); default ``.{name}.tmp-{pid}``. A failure removes
    the temp file and leaves ``path`` as it was. Out: ``path``.
    """
    path = Path(path)
    tmp = Path(tmp) if tmp is not None else path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write_bytes(tmp, data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):  # a read-only folder: the clean-up's own error must not hide the first
            tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)
    return path


def sha256_file(path: str | os.PathLike) -> str:
    """The hex sha256 of the file at ``path``."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def save_tensors(path: str | os.PathLike, tensors: dict, metadata: dict[str, str] | None = None) -> Path:
    """``tensors`` (name -> tensor; copied to the CPU, contiguous) as a safetensors file at ``path``, atomically."""
    from safetensors.torch import save

    data = save({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, metadata=metadata)
    return replace_bytes(path, data)


def load_tensors(path: str | os.PathLike) -> tuple[dict, dict[str, str]]:
    """``(tensors, metadata)`` of a safetensors file, or of a legacy torch file (a dict of tensors, loaded with
    ``weights_only=True``; metadata ``{}``) recognised by its content; ValueError naming ``path`` if unreadable."""
    import torch

    path = Path(path)
    data = path.read_bytes()
    if data[:2] == b"PK" or data[:1] == b"\x80":  # a torch zip archive, or a legacy pickle
        try:
            tensors = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - unpickling errors of every kind: the file and the reason
            raise ValueError(f"refusing {path}: {_reason(e)}") from None
        if not isinstance(tensors, dict):
            raise ValueError(f"refusing {path}: it holds a {type(tensors).__name__}, not a dict of tensors")
        return tensors, {}
    from safetensors import safe_open
    from safetensors.torch import load

    try:
        tensors = load(data)
        with safe_open(path, framework="pt") as f:
            metadata = dict(f.metadata() or {})
    except Exception as e:  # noqa: BLE001 - a truncated or foreign file
        raise ValueError(f"refusing {path}: not a readable safetensors file (truncated or corrupt: "
                         f"{' '.join(str(e).split())[:160]})") from None
    return tensors, metadata


def _reason(error: BaseException) -> str:
    text = " ".join(str(error).split())
    if "WeightsUnpickler error" in text:  # torch's refusal: its reason, not its advice to load unsafely
        reason = text.split("WeightsUnpickler error:", 1)[1].split(" was not an allowed global")[0]
        return f"not plain tensor data ({reason.strip()[:160]})"
    return f"truncated or corrupt ({type(error).__name__}: {text[:160]})"


__all__ = ["fsync_path", "load_tensors", "replace_bytes", "save_tensors", "sha256_file", "write_bytes"]
