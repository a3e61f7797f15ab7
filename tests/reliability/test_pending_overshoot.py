"""Issue 45, case 8: a resume from a pending batch (an episode that ended mid-batch before a kill) must not overshoot
``collector.total_frames``.

Before: after the pending batch's short ``k`` steps, the collector counted whole batches from there, so the
resumed run ended ``frames_per_batch - k`` frames past its total (2,538 of 2,500 in the issue).
"""

from __future__ import annotations

import pytest
from _runs import train
from test_pending_episodes import kill_with_pending_episode

from pe_rlhf.runtime.checkpoint import find_checkpoint

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


def test_a_resume_from_a_pending_batch_ends_at_total_frames(tmp_path):
    killed = tmp_path / "killed"
    start, end = kill_with_pending_episode(killed, 125)
    assert start < end <= start + 25
    total = end + 30  # the collector's whole 25-frame batches from ``end`` reach end + 50
    final = train(killed, f"collector.total_frames={total}", resume=True)
    assert final["training"]["frames"] == total
    assert find_checkpoint(killed / "checkpoints").name == f"ckpt_{total:09d}"
    rows = [int(float(line.split(",")[0])) for line in (killed / "metrics.csv").read_text().splitlines()[1:]]
    assert rows[-1] == total and max(rows) == total
