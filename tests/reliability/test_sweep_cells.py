"""Issue 45, case 3: sweep cells die with their driver, and a rerun never starts a second writer on a live cell.

Before: a ``pe-rlhf sweep ... --backend processes`` driver killed with SIGKILL left its cell running (parent 1), and
rerunning the sweep, as the docs advise, started ``--resume`` on that cell while it still ran: two writers, and the
sweep reported the cell finished.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _runs import TINY
from _scripts import SCRIPT_ENV

from pe_rlhf.runtime.run_folder import folder_holder

CELL = "pe-rlhf__s0"


def sweep_file(tmp_path: Path, frames: int) -> Path:
    config = tmp_path / "tiny.yaml"
    config.write_text(json.dumps({"name": "tiny", "base": [*TINY, f"collector.total_frames={frames}"], "seeds": [0],
                                  "methods": ["pe-rlhf"], "metrics": ["success_rate"]}))
    return config


def sweep(config: Path, out: Path, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pe_rlhf.apps.cli", "sweep", str(config), "--backend", "processes",
                             "--max-parallel", "1", "--no-progress", "--out", str(out)], env=SCRIPT_ENV,
                            cwd=config.parent, **kwargs)


def wait_until(condition, timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if condition():
            return
        time.sleep(0.1)
    pytest.fail(f"timed out waiting for {what}")


def test_a_killed_driver_takes_its_cells_along(tmp_path):
    out = tmp_path / "out"
    driver = sweep(sweep_file(tmp_path, 20000), out, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: folder_holder(out / CELL) is not None, 120, "the cell to hold its folder")
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        wait_until(lambda: folder_holder(out / CELL) is None, 20, "the cell to die with its driver")
    finally:
        if driver.poll() is None:
            driver.kill()
            driver.wait()


def test_a_rerun_does_not_start_a_second_writer_on_a_live_cell(tmp_path):
    out, config = tmp_path / "out", sweep_file(tmp_path, 20000)
    first = sweep(config, out, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: folder_holder(out / CELL) is not None, 120, "the cell to hold its folder")
        log = (out / "logs" / f"{CELL}.log").read_text()
        rerun = sweep(config, out, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        printed = rerun.communicate(timeout=120)[0]
        assert rerun.returncode == 1, printed
        assert "still running (pid " in printed and "0 finished now, 1 failed" in printed, printed
        assert (out / "logs" / f"{CELL}.log").read_text().count("=== ") == log.count("=== ") == 1  # no second start
        assert folder_holder(out / CELL) is not None and first.poll() is None  # the live cell ran on, untouched
    finally:
        first.kill()
        first.wait()
