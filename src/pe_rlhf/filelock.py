"""``FileLock``: an exclusive advisory lock on a file, held by one object: a thin layer over py-filelock.

py-filelock (the ``filelock`` package, a dependency of torch) does the locking: ``fcntl.flock`` on POSIX,
``msvcrt.locking`` on Windows. This module keeps the project's one meaning of a lock on top of it:

- advisory: it keeps out other ``FileLock`` holders of the same path (in this or another process), not readers or
  writers that do not ask for it;
- the lock belongs to the object: two ``FileLock`` objects on one path contend even within one process or one
  thread, and acquiring a lock the object already holds is an error, not a nested hold (py-filelock counts nested
  holds; a second writer in the same process must wait instead);
- the OS releases it when the holder's file is closed or its process dies: a killed recorder or checkpoint writer
  leaves no stale lock (py-filelock's fallback to a lock file whose mere existence is the lock, which a dead
  process would leave behind, is turned off);
- the lock file is created if missing and never deleted (deleting it would let a second holder lock a new file).
"""

from __future__ import annotations

import os
from pathlib import Path

import filelock


class FileLock:
    """An exclusive advisory lock on ``path`` (see the module docstring).

    ``acquire()`` waits for the lock; ``acquire(blocking=False)`` returns False at once when another
    holder has it. ``with FileLock(path):`` waits, holds, and releases on exit. Not re-entrant:
    acquiring a lock this object already holds raises RuntimeError.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        # thread_local=False: the object, not the thread, holds it (a writer thread may release what it took)
        self._lock = filelock.FileLock(self.path, thread_local=False, is_singleton=False, fallback_to_soft=False,
                                       preserve_lock_file=True)

    @property
    def locked(self) -> bool:
        """Whether this object holds the lock."""
        return self._lock.is_locked

    def acquire(self, blocking: bool = True) -> bool:
        """Take the lock (creating the file); True once held, False if ``blocking=False`` and it is taken."""
        if self._lock.is_locked:
            raise RuntimeError(f"FileLock({str(self.path)!r}) is already held by this object")
        try:
            self._lock.acquire(blocking=blocking)
        except filelock.Timeout:
            return False
        return True

    def release(self) -> None:
        """Give the lock up (a no-op when not held)."""
        if self._lock.is_locked:
            self._lock.release(force=True)

    def __enter__(self) -> FileLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"FileLock({str(self.path)!r}, locked={self.locked})"


__all__ = ["FileLock"]
