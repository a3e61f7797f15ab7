"""``pe_rlhf.threads``: the updates take the cores other processes leave, and OpenMP threads sleep."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from pe_rlhf import threads


class FakeClock:
    def __init__(self):
        self.wall = self.cpu = 0.0

    def monotonic(self):
        return self.wall

    def process_time(self):
        return self.cpu


def test_free_cores_subtracts_what_other_processes_use(monkeypatch):
    clock, busy = FakeClock(), {"seconds": 0.0}
    monkeypatch.setattr(threads, "time", clock)
    free = threads.FreeCores(limit=4, busy=lambda: busy["seconds"])
    free.cores = 4
    # 1 s: all 4 cores busy (4 core-seconds), 1 of them ours: 3 cores taken by others -> 1 thread
    clock.wall, clock.cpu, busy["seconds"] = 1.0, 1.0, 4.0
    assert free() == 1
    # next second: only our own core busy -> all 4 free again (capped at the limit)
    clock.wall, clock.cpu, busy["seconds"] = 2.0, 2.0, 5.0
    assert free() == 4
    # next second: one other process busy besides us -> 3
    clock.wall, clock.cpu, busy["seconds"] = 3.0, 3.0, 7.0
    assert free() == 3
    # a call within min_interval keeps the last answer; an unreadable busy time gives the limit
    clock.wall = 3.1
    assert free() == 3
    busy["seconds"] = None
    clock.wall = 5.0
    assert free() == 4


def test_busy_seconds_counts_every_core_but_idle_time():
    """psutil's counters: the busy time grows by at most (cores x wall time) while this process spins."""
    import time

    import psutil

    before, start = threads.busy_seconds(), time.monotonic()
    sum(i * i for i in range(300_000))
    after, wall = threads.busy_seconds(), time.monotonic() - start
    times = psutil.cpu_times()
    assert before is not None and after is not None and 0.0 <= after - before <= (psutil.cpu_count() + 1) * wall + 0.1
    assert after < sum(getattr(times, f) for f in times._fields)  # idle time is not busy


def test_free_cores_on_this_machine_counts_another_busy_process():
    """On the real busy times (psutil): a child spinning on one core for the whole window takes a core away (a
    FreeCores that ignored the other process, or answered its limit, fails here)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 0
    if cores < 2:
        pytest.skip("needs 2 cores: with one, every answer is 1")
    spin = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 3: pass"])
    try:
        time.sleep(0.3)  # the child is spinning before the window opens
        free = threads.FreeCores(limit=cores, min_interval=0.0)
        time.sleep(1.0)
        assert free() <= cores - 1
    finally:
        spin.kill()
        spin.wait()


def test_thread_budget():
    assert threads.thread_budget(3)() == 3
    assert isinstance(threads.thread_budget("auto"), threads.FreeCores)


@pytest.mark.parametrize("env, expected", [({}, "unset"), ({"OMP_WAIT_POLICY": "PASSIVE"}, "PASSIVE"),
                                           ({"GOMP_SPINCOUNT": "3000"}, "unset")])
def test_importing_pe_rlhf_leaves_openmp_waiting_as_the_user_set_it(env, expected):
    """GNU OpenMP's default spin-waiting is faster on idle cores and, with the thread count following the load,
    no longer collapses on a busy one (docs/results/run_time_spin.json), so importing sets nothing."""
    clean = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    out = subprocess.run([sys.executable, "-c", "import pe_rlhf, os; print(os.environ.get('OMP_WAIT_POLICY', 'unset'), "
                          "os.environ.get('GOMP_SPINCOUNT', 'unset'))"],
                         env={**clean, **env}, capture_output=True, text=True, check=True)
    assert out.stdout.split() == [expected, env.get("GOMP_SPINCOUNT", "unset")]


def test_sync_updater_asks_the_budget_before_each_round():
    import torch
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from pe_rlhf.algorithms.proxy_q.background_updates import SyncUpdater

    asked, seen = [], []

    def budget():
        asked.append(len(asked) % 2 + 1)  # 1, 2, 1, ...
        return asked[-1]

    class Loss(torch.nn.Module):  # records the thread count each update runs on
        def __init__(self):
            super().__init__()
            self.net = torch.nn.Linear(2, 1)

        def forward(self, td):
            seen.append(torch.get_num_threads())
            return TensorDict({"loss_q": self.net(td["x"]).pow(2).mean()}, [])

    loss = Loss()
    net = loss.net
    opt = torch.optim.SGD(net.parameters(), 0.1)

    class NoTargets:  # the Polyak step of a loss without target networks
        def step(self):
            pass

    replay = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4)
    replay.extend(TensorDict({"x": torch.randn(10, 2)}, [10]))
    before = torch.get_num_threads()
    updater = SyncUpdater(loss, {"q": opt}, NoTargets(), replay, updates_per_step=1, max_grad_norm=None, actor=net,
                          threads=budget)
    for _ in range(3):
        updater.notify_frames(2)
    assert asked == [1, 2, 1, 2]  # once at construction, then once per round
    assert seen == [2, 2, 1, 1, 2, 2] and updater.threads == 2
    assert torch.get_num_threads() == before  # acting keeps its own count
