"""Issue 45, case 1: a run killed before its first checkpoint resumes from its journal alone.

A child trains (checkpoint at frame 100, 25-frame batches) and is killed once its journal holds frame 75, before
any checkpoint is complete. ``--resume`` replays the journaled batches from frame 0 through a fresh learner of the
same seed; an uninterrupted run to the same frame is the reference: buffers, counters, networks, optimisers and
RNG states identical, and the curve has every row once.
"""

from __future__ import annotations

import pytest
from _compare import assert_same
from _runs import checkpoint_contents, train
from test_kill_resume import kill_when_journaled

from pe_rlhf.runtime.checkpoint import list_checkpoints
from pe_rlhf.runtime.journal import BatchJournal

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


def test_a_run_killed_before_its_first_checkpoint_resumes_from_the_journal(tmp_path, capsys):
    killed = tmp_path / "killed"
    kill_when_journaled(killed, 75, checkpoint_every=1000)
    ckpts = killed / "checkpoints"
    assert not list_checkpoints(ckpts)  # nothing but the journal
    journaled = [end for end, _ in BatchJournal(ckpts / "journal").files()]
    last = max(journaled)
    assert journaled == list(range(25, last + 1, 25)) and last >= 75, journaled

    final = train(killed, f"collector.total_frames={last}", "checkpoint.every_frames=1000", resume=True)
    assert "replaying the journal's" in capsys.readouterr().out
    assert final["training"]["frames"] == last  # every journaled batch is back, none collected twice
    reference = train(tmp_path / "uninterrupted", f"collector.total_frames={last}", "checkpoint.every_frames=1000")
    resumed = checkpoint_contents(ckpts / f"ckpt_{last:09d}")
    uninterrupted = checkpoint_contents(tmp_path / "uninterrupted" / "checkpoints" / f"ckpt_{last:09d}")
    assert len(resumed["replay"]) == last
    assert_same(uninterrupted, resumed, "killed before the first checkpoint")
    assert reference["training"]["frames"] == last
    rows = [line.split(",")[0] for line in (killed / "metrics.csv").read_text().splitlines()[1:]]
    assert [int(float(r)) for r in rows] == list(range(25, last + 1, 25))
