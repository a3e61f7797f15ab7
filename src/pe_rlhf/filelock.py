"""``FileLock``: an exclusive advisory lock on a file, on POSIX (``fcntl.flock``) and Windows (``msvcrt.locking``).

Advisory: it keeps out other ``FileLock`` holders of the same path (in this or another process), not
readers or writers that do not ask for it. The lock belongs to the open file, so two ``FileLock``
objects on one path contend even within one process, and the OS releases it when the holder's file
is closed or its process dies (a killed recorder or checkpoint writer leaves no stale lock). The lock
file is created if missing and never deleted (deleting it would let a second holder lock a new file).
On Windows the lock covers the file's first byte (``msvcrt.locking`` locks byte ranges; the range
may lie beyond the end of the empty file).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

if os.name == "nt":
    import msvcrt

    def _try_lock(fd: int) -> bool:
        os.lseek(fd, 0, os.SEEK_SET)  # msvcrt locks from the current position
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError:
            return False
        return True

    def _unlock(fd: int) -> None:
        os.lseek(fd, 0, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)

    def _lock(fd: int) -> None:
        while not _try_lock(fd):  # LK_LOCK gives up after 10 s; a checkpoint write may take longer
            time.sleep(0.05)
else:
    import fcntl

    def _try_lock(fd: int) -> bool:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        return True

    def _unlock(fd: int) -> None:
        fcntl.flock(fd, fcntl.LOCK_UN)

    def _lock(fd: int) -> None:
        fcntl.flock(fd, fcntl.LOCK_EX)


class FileLock:
    """An exclusive advisory lock on ``path`` (see the module docstring).

    ``acquire()`` waits for the lock; ``acquire(blocking=False)`` returns False at once when another
    holder has it. ``with FileLock(path):`` waits, holds, and releases on exit. Not re-entrant:
    acquiring a lock this object already holds raises RuntimeError.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._fd: int | None = None

    @property
    def locked(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def acquire(self, blocking: bool = True) -> bool:
        """Take the lock (creating the file); True once held, False if ``blocking=False`` and it is taken."""
        if self._fd is not None:
            raise RuntimeError(f"FileLock({str(self.path)!r}) is already held by this object")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if blocking:
                _lock(fd)
            elif not _try_lock(fd):
                os.close(fd)
                return False
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        return True

    def release(self) -> None:
        """Give the lock up (a no-op when not held)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            _unlock(fd)
        finally:
            os.close(fd)

    def __enter__(self) -> FileLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"FileLock({str(self.path)!r}, locked={self.locked})"


__all__ = ["FileLock"]
