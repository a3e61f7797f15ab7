"""One writer per run folder: a lock held for the run's whole life, and what a second writer is told.

``with hold_run_folder(out):`` creates ``out`` if needed, refuses a symlink in it that leads out of it (a write
through it would change a file elsewhere), takes an exclusive lock on ``out/.run.lock``
(:class:`~pe_rlhf.filelock.FileLock`: the OS releases it when the process dies, so a killed run leaves no stale
lock) and writes who holds it to ``out/.run.holder`` (JSON: ``pid``, ``host``, ``started``, ``command``). A second
run on the same folder, fresh or ``--resume``, gets :class:`RunFolderBusy` (a
:class:`~pe_rlhf.runtime.config_rules.ConfigError`: one ``error:`` line, exit 2) naming the holder, before it writes
anything. :func:`folder_holder` asks without taking the lock (a sweep checks a cell before it starts one).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from pe_rlhf import durable
from pe_rlhf.filelock import FileLock
from pe_rlhf.runtime.config_rules import ConfigError

LOCK_FILE, HOLDER_FILE = ".run.lock", ".run.holder"

__all__ = ["HOLDER_FILE", "LOCK_FILE", "RunFolderBusy", "check_links", "folder_holder", "hold_run_folder"]


class RunFolderBusy(ConfigError):
    """Another process holds the run folder (the message names it)."""


def _describe_holder(out: Path) -> str:
    try:
        h = json.loads((out / HOLDER_FILE).read_text())
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(h["started"])))
        return f"pid {int(h['pid'])} on {h['host']}, started {started}: {h['command'][:160]}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that has not yet said who it is"


def folder_holder(out: str | os.PathLike) -> str | None:
    """Who holds the run folder ``out`` now (a line), or None when no run holds it."""
    out = Path(out)
    if not (out / LOCK_FILE).is_file():
        return None
    probe = FileLock(out / LOCK_FILE)
    if probe.acquire(blocking=False):
        probe.release()
        return None
    return _describe_holder(out)


def check_links(out: Path) -> None:
    """ConfigError naming the first symlink in ``out`` (recursively) that resolves outside ``out``."""
    root = out.resolve()
    for dirpath, dirnames, filenames in os.walk(out):
        for name in (*dirnames, *filenames):
            path = Path(dirpath) / name
            if path.is_symlink() and not path.resolve().is_relative_to(root):
                raise ConfigError(f"{path} is a symlink to {path.resolve()}, outside the run folder {out}: a run "
                                  "writes only inside its folder; remove the link (or copy the file in) first")


@contextlib.contextmanager
def hold_run_folder(out: str | os.PathLike) -> Iterator[Path]:
    """Hold ``out`` for this process (module docstring); RunFolderBusy if another run holds it."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lock = FileLock(out / LOCK_FILE)
    if not lock.acquire(blocking=False):
        raise RunFolderBusy(f"{out} is in use by another run ({_describe_holder(out)}); one run writes a folder at "
                            "a time: wait for it to finish, stop it, or pass another --out")
    try:
        check_links(out)
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time(),
                  "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])}
        durable.replace_bytes(out / HOLDER_FILE, json.dumps(holder).encode())
        yield out
    finally:
        lock.release()
