"""Issue 45, case 7: a checkpoint holds the replay buffers' filled rows only, and a buffer that cannot fit is
refused before anything is written, naming the field and the estimate.

Before: a checkpoint was the size of the buffers' capacity (448 MB for 500 rows at ``replay_buffer.size=100000``:
the unused rows are uninitialised memory, written anyway), and ``replay_buffer.size=10**10`` was accepted and
failed after the run folder existed, with an allocator traceback.
"""

from __future__ import annotations

import pytest
from _runs import checkpoint_contents, train
from _scripts import run_recipe

from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.runtime.world import obs_dim

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


def folder_bytes(path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def test_a_checkpoint_is_the_size_of_its_rows_not_of_the_capacity(tmp_path):
    out = tmp_path / "run"
    train(out, "collector.total_frames=100", "replay_buffer.size=100000")
    ckpt = out / "checkpoints" / "ckpt_000000100"
    row = 2 * 4 * obs_dim(load_config(overrides=["profile=smoke"]))  # observation and next observation, float32
    buffers = sum(folder_bytes(d) for d in ckpt.glob("buffer_*"))
    assert buffers < 150 * row  # 150 rows (100 replay, 50 warm-up), uncompressed; the capacity is 100000
    contents = checkpoint_contents(ckpt)  # and it loads back whole, into buffers of the full capacity
    assert len(contents["replay"]) == 100 and len(contents["warmup"]) == 50
    resumed = train(out, "collector.total_frames=150", resume=True)
    assert resumed["training"]["frames"] == 150


def test_a_buffer_that_cannot_fit_is_refused_before_anything_is_written(tmp_path):
    out = tmp_path / "never"
    result = run_recipe("pe_rlhf", "profile=smoke", "replay_buffer.size=10000000000", "--out", str(out), cwd=tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: replay_buffer.size=10000000000 is invalid"), lines
    assert " GB (" in lines[0] and "memory" in lines[0]
    assert not out.exists()
