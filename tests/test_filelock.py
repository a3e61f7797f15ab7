"""``FileLock``: exclusive between file objects and between processes, non-blocking refusal, release on
close and on process death; the recorder and the checkpoint writer hold it."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pe_rlhf.filelock import FileLock

SRC = str(Path(__file__).resolve().parents[1] / "src")

# Holds the lock on argv[1], says so on stdout, then waits for stdin to close (or is killed).
HOLDER = textwrap.dedent("""
    import sys
    sys.path.insert(0, sys.argv[2])
    from pe_rlhf.filelock import FileLock
    lock = FileLock(sys.argv[1])
    assert lock.acquire(blocking=False)
    print("held", flush=True)
    sys.stdin.read()
""")


def _holder(path: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(path), SRC], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_two_file_objects_contend_and_release_hands_over(tmp_path):
    path = tmp_path / ".lock"
    first, second = FileLock(path), FileLock(path)
    assert first.acquire(blocking=False) and first.locked and path.exists()
    assert second.acquire(blocking=False) is False and not second.locked
    with pytest.raises(RuntimeError, match="already held"):
        first.acquire()
    first.release()
    first.release()  # a no-op once released
    assert second.acquire(blocking=False)
    second.release()
    with FileLock(path) as held:  # the context manager waits, holds, releases
        assert held.locked and not FileLock(path).acquire(blocking=False)
    assert not held.locked and FileLock(path).acquire(blocking=False)


@pytest.mark.timeout(60)
def test_another_process_holding_it_refuses_then_blocks_until_released(tmp_path):
    path = tmp_path / ".lock"
    proc = _holder(path)
    try:
        assert FileLock(path).acquire(blocking=False) is False
        proc.stdin.close()  # the holder exits: the OS drops its lock ...
        start = time.perf_counter()
        lock = FileLock(path)
        assert lock.acquire()  # ... so a blocking acquire returns (it may wait for the exit)
        assert time.perf_counter() - start < 30
        lock.release()
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.timeout(60)
def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    path = tmp_path / ".lock"
    proc = _holder(path)
    assert not FileLock(path).acquire(blocking=False)
    proc.kill()
    proc.wait()
    assert FileLock(path).acquire(blocking=False)


def test_the_recorder_holds_the_directory_lock(tmp_path):
    from pe_rlhf.envs import DrivingConfig
    from pe_rlhf.mentors.recording import DemonstrationRecorder

    config = DrivingConfig(horizon=20)
    with DemonstrationRecorder(tmp_path / "demos", config, "professional", seeds=[0]):
        assert not FileLock(tmp_path / "demos" / ".lock").acquire(blocking=False)
        with pytest.raises(RuntimeError, match="another process is recording into"):
            DemonstrationRecorder(tmp_path / "demos", config, "professional", seeds=[0])
    assert FileLock(tmp_path / "demos" / ".lock").acquire(blocking=False)  # closed: released


def test_a_checkpoint_write_waits_for_the_lock(tmp_path):
    """``save_checkpoint`` writes under the directory's lock: held elsewhere, the write waits for it."""
    import threading

    import torch

    from pe_rlhf.runtime.checkpoint import find_checkpoint, save_checkpoint

    directory = tmp_path / "checkpoints"
    directory.mkdir()
    outside = FileLock(directory / ".lock")
    assert outside.acquire()
    writer = threading.Thread(target=save_checkpoint, args=(directory,),
                              kwargs={"step": 100, "modules": {"net": torch.nn.Linear(2, 1)}, "optimizers": {}})
    writer.start()
    writer.join(timeout=1.0)
    assert writer.is_alive() and find_checkpoint(directory) is None  # blocked on the lock
    outside.release()
    writer.join(timeout=30)
    assert not writer.is_alive() and find_checkpoint(directory) is not None
    assert FileLock(directory / ".lock").acquire(blocking=False)  # the writer released it


def test_the_object_not_the_thread_holds_it_and_the_file_stays(tmp_path):
    """A lock taken in one thread is held by the object in every thread (a writer thread may release it); the
    lock file is never deleted, so a later holder locks the same file."""
    import threading

    path = tmp_path / ".lock"
    lock = FileLock(path)
    assert lock.acquire(blocking=False)
    seen = []
    other = threading.Thread(target=lambda: (seen.append(lock.locked), lock.release()))
    other.start()
    other.join(timeout=10)
    assert seen == [True] and not lock.locked
    assert path.exists() and FileLock(path).acquire(blocking=False)
