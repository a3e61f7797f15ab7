"""Issue 45, cases 2 and 6: one writer per run folder, and no write through a symlink that leaves it.

A run holds its folder for its whole life; a second ``train.py`` on the same ``--out`` (fresh or ``--resume``)
exits 2 with one line naming the holder, before writing anything, and the first run's config stays its own.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from _runs import RECIPE, start_training
from _scripts import run_recipe, run_recipe_here

from pe_rlhf.runtime.run_folder import HOLDER_FILE, folder_holder

pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning")]


def wait_for_holder(out: Path, proc, timeout: float = 120.0) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if (out / HOLDER_FILE).is_file() and folder_holder(out) is not None:
            return json.loads((out / HOLDER_FILE).read_text())
        time.sleep(0.05)
    pytest.fail(f"the first run never held {out} (rc {proc.poll()})")


def test_a_second_writer_is_refused_in_one_line_naming_the_holder(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    # runs past both refusals, paced to 10 steps a second: a holder that sleeps leaves the cores to the refused runs
    first = start_training(out, "collector.total_frames=20000", "collector.realtime_hz=10", "seed=0")
    try:
        holder = wait_for_holder(out, first)
        assert holder["pid"] == first.pid
        second = run_recipe("pe_rlhf", "profile=smoke", "seed=1", "--out", str(out), cwd=tmp_path)  # a fresh process
        resumed = run_recipe_here("pe_rlhf", "--resume", str(out), monkeypatch=monkeypatch, capsys=capsys)  # in here
        for code, stderr in ((second.returncode, second.stderr), resumed[::2]):
            assert code == 2, stderr[-2000:]
            lines = stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("error: ") and f"pid {first.pid}" in lines[0], lines
            assert "in use by another run" in lines[0]
        assert first.poll() is None  # the holder ran on, untouched
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert "seed: 0" in (out / "config.yaml").read_text()
    assert folder_holder(out) is None  # released when its process ended


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    out = tmp_path / "run"
    first = start_training(out, "collector.total_frames=300")
    wait_for_holder(out, first)
    first.kill()
    first.wait()
    assert folder_holder(out) is None
    assert RECIPE.is_file()
