"""Running the cells without Ray: one spawned process per cell on this machine, at most ``max_parallel`` at once,
optionally until a deadline (``pe-rlhf sweep --backend processes [--deadline SECONDS]``).

For a machine where Ray is not installed or not wanted (a lent GPU machine with a fixed time budget, a laptop).
Each process runs :func:`pe_rlhf.apps.sweeps.execution.run_cell`, the body of a Ray task, so a cell's folder,
log and resume behave exactly as under Ray: a cell that fails or is stopped is left unfinished and the next
invocation reruns it (from its newest checkpoint when it has one). A cell still running at the deadline is
killed; its ``metrics.csv`` shows how far it got.

Cells die with their driver: each runs in a process group of its own, killed whole when the driver stops it, and
on Linux with the parent-death signal armed, so a driver killed with SIGKILL takes its cells along. A rerun
never starts a second writer on a live cell: a cell whose folder another process holds
(:func:`~pe_rlhf.runtime.run_folder.folder_holder`) is reported as failed, "still running", and not started.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import sys
import time
from pathlib import Path

from pe_rlhf.apps.sweeps.cells import Cell, cell_dir, log_path, plan, write_record
from pe_rlhf.apps.sweeps.execution import THREAD_VARS, SweepReport, run_cell, running_text
from pe_rlhf.runtime.run_folder import folder_holder

POLL_SECONDS = 1.0


def _die_with(parent: int) -> None:
    """This process (and, through its own process group, the driver's clean-up) ends when ``parent`` dies, even by
    SIGKILL: Linux's parent-death signal. Elsewhere only the driver's clean-up stops a cell."""
    os.setpgid(0, 0)  # a group of its own: the driver kills the cell with everything it started
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the driver died before the signal was armed
        os._exit(1)


def _cell_process(cell: Cell, out: str, threads: int, parent: int) -> None:
    _die_with(parent)
    for var in THREAD_VARS:  # before torch is imported in this fresh (spawned) interpreter
        os.environ[var] = str(threads)
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    run_cell(cell, out, threads)


def _kill_group(process) -> None:
    """Kill a cell's process and every process in its group (its collector workers), then reap it."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(process.pid, signal.SIGKILL)
    process.kill()
    process.join()


def _last_line(path: Path) -> str:
    """The log's last non-empty line (a traceback's exception), '' when there is none."""
    try:
        lines = [line.strip() for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return lines[-1] if lines else ""


def run_cells_in_processes(cells: list[Cell], out: str | Path, *, max_parallel: int | None = None,
                           num_cpus: float = 1.0, progress: bool = True, name: str = "sweep",
                           deadline: float | None = None) -> SweepReport:
    """Run every unfinished cell in a process of its own, writing to ``out/<cell>/``; finished cells are skipped.

    ``max_parallel``: processes at once (None: this machine's CPUs // ``num_cpus``). ``deadline``: seconds from
    now after which running cells are killed and the rest left unstarted (``report.stopped`` names both).
    """
    from tqdm import tqdm

    out = Path(out)
    finished, todo = plan(out, cells)
    report = SweepReport(skipped=[c.name for c in finished])
    if not todo:
        return report
    threads = max(1, int(num_cpus))
    capacity = max_parallel or max(1, int((os.cpu_count() or 1) // num_cpus))
    context = multiprocessing.get_context("spawn")  # a clean interpreter a cell, as a Ray worker is
    started, pending, running = time.monotonic(), list(todo), {}
    bar = tqdm(total=len(cells), initial=len(finished), desc=name, unit="cell", disable=not progress,
               dynamic_ncols=True)
    try:
        while pending or running:
            if deadline is not None and time.monotonic() - started >= deadline:
                break
            while pending and len(running) < capacity:
                cell = pending.pop(0)
                holder = folder_holder(cell_dir(out, cell))
                if holder is not None:  # a cell of an earlier driver still runs: never a second writer
                    report.failed[cell.name] = f"still running ({holder}); not started again"
                    bar.write(f"BUSY   {cell.name}: {report.failed[cell.name]}")
                    bar.update(1)
                    continue
                write_record(out, cell)
                process = context.Process(target=_cell_process,
                                          args=(cell, str(out.resolve()), threads, os.getpid()),
                                          name=cell.name, daemon=False)
                process.start()
                running[cell.name] = (process, cell, time.monotonic())
            bar.set_postfix_str(running_text(list(running)))
            for cell_name, (process, cell, since) in list(running.items()):
                if process.is_alive():
                    continue
                process.join()
                del running[cell_name]
                if process.exitcode == 0:
                    report.finished[cell_name] = time.monotonic() - since
                    bar.write(f"done   {cell_name} ({report.finished[cell_name]:.0f} s)")
                else:
                    report.failed[cell_name] = f"exit code {process.exitcode}: {_last_line(log_path(out, cell))}"
                    bar.write(f"FAILED {cell_name}: {report.failed[cell_name]} (log: {log_path(out, cell)})")
                bar.update(1)
            time.sleep(POLL_SECONDS if running else 0)
    finally:
        for cell_name, (process, _, _) in running.items():
            _kill_group(process)
            report.stopped.append(cell_name)
        report.stopped += [c.name for c in pending]
        for cell_name in report.stopped:
            bar.write(f"stopped {cell_name}" + (" at the deadline" if deadline is not None else ""))
        bar.set_postfix_str("")
        bar.close()
    return report


__all__ = ["run_cells_in_processes"]
