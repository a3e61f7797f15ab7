"""Intra-op thread control that degrades gracefully on a shared machine.

- :func:`torch_threads`: run a block with ``n`` intra-op threads (acting runs on one).
- :class:`FreeCores`: how many cores other processes leave free, from every core's busy time (psutil's
  ``cpu_times``, on any OS) less this process's own, so the updates take their share of a busy machine instead
  of fighting for it.

Why the count must follow the load (a batch-256 MLP update, 2 cores, ``docs/experiments/speed.md``): with
both cores busy with other jobs, 2 threads took 582 ms an update under GNU OpenMP's default spin-waiting
(a thread spins at each barrier for a partner that is not running), against 28 ms on 1 thread. With the
cores idle, 2 spinning threads took 24 ms, 1 thread 30 ms. ``OMP_WAIT_POLICY=PASSIVE`` (threads sleep at
barriers) avoids the collapse (36 ms busy) but costs the idle case (38 ms: a wake-up per parallel
region). With the count following the load, spin-waiting no longer collapses (a 2,000-step run with one core
busy: 0.71 of its idle rate under GNU's default, against 1.33 passive, ``docs/results/run_time_spin.json``) and
runs 1.7x faster on idle cores, so ``import pe_rlhf`` leaves OpenMP's waiting as it is (until 2026-12-04 it set
``OMP_WAIT_POLICY=PASSIVE``). A paced ``optim.async_updates`` run keeps its 50 Hz either way
(``tests/algorithms/proxy_q/test_realtime.py``); set ``OMP_WAIT_POLICY=PASSIVE`` yourself where other jobs
start and stop faster than the count follows them.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable

import psutil
import torch

@contextlib.contextmanager
def torch_threads(n: int):
    """Run a block with ``n`` intra-op torch threads, restoring the previous count afterwards.

    Acting runs single-threaded: its matmuls are tiny, and on two busy cores a second thread made
    each selector call ~10x slower (measured: 35 vs 284 env steps/s); batch-1024 updates gain from
    every thread.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def busy_seconds() -> float | None:
    """Core-seconds every process has kept the cores busy since boot (all but idle and I/O wait), from psutil's
    ``cpu_times``; None where the OS will not say (a restricted ``/proc``)."""
    try:
        t = psutil.cpu_times()
    except (OSError, psutil.Error):
        return None
    idle = t.idle + getattr(t, "iowait", 0.0)
    # guest times are already counted in user/nice (Linux), as /proc/stat's sum would double them
    total = sum(getattr(t, f) for f in t._fields if f not in ("guest", "guest_nice"))
    return total - idle


def _affinity_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    try:
        return len(psutil.Process().cpu_affinity())
    except (AttributeError, OSError, psutil.Error):  # macOS has no affinity
        return os.cpu_count() or 1


class FreeCores:
    """The cores other processes leave free since the previous call, as an intra-op thread count.

    ``FreeCores(limit)()`` returns an int in ``[1, limit]`` (``limit``: default ``torch.get_num_threads()``
    at construction): this machine's cores (the process's CPU affinity) minus the cores the *other*
    processes kept busy over the interval since the last call (every core's busy time, :func:`busy_seconds`,
    less this process's own CPU time). Calls closer than ``min_interval`` seconds return the previous answer;
    where the busy time cannot be read it returns ``limit``. ``busy`` replaces :func:`busy_seconds` (tests).

    psutil reads what ``/proc/stat`` holds on Linux (this class read it itself until 2026-12-06) and the same
    counters on macOS and Windows; the arithmetic of "the others' share" is this class's.
    """

    def __init__(self, limit: int | None = None, min_interval: float = 0.5,
                 busy: Callable[[], float | None] = busy_seconds):
        self.limit = max(1, int(limit if limit is not None else torch.get_num_threads()))
        self.min_interval = float(min_interval)
        self.busy = busy
        self.cores = _affinity_cores()
        self.count = self.limit
        self._last = self._sample()

    def _sample(self) -> tuple[float, float | None, float]:
        return time.monotonic(), self.busy(), time.process_time()

    def __call__(self) -> int:
        now = self._sample()
        wall = now[0] - self._last[0]
        if now[1] is None or self._last[1] is None:
            return self.limit
        if wall < self.min_interval:
            return self.count
        own = now[2] - self._last[2]
        others = max(0.0, (now[1] - self._last[1]) - own) / wall  # cores the other processes kept busy
        self._last = now
        self.count = max(1, min(self.limit, self.cores - round(others)))
        return self.count


def thread_budget(setting: int | str, limit: int | None = None):
    """A callable returning the updates' intra-op thread count for ``optim.threads``: a fixed count for an
    int, :class:`FreeCores` (at most ``limit``) for ``"auto"``."""
    if setting == "auto":
        return FreeCores(limit)
    count = int(setting)
    return lambda: count


__all__ = ["FreeCores", "thread_budget", "torch_threads"]
