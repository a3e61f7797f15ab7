"""Issue 45, case 8: a resume from a pending batch (an episode that ended mid-batch before a kill) ends at
``collector.total_frames`` and keeps the run's rows on the ``collector.frames_per_batch`` grid.

Before: the pending batch's ``k`` steps were trained on as a short batch and the collector counted whole batches
from there, so the resumed run ended ``frames_per_batch - k`` frames past its total (2,538 of 2,500 in the issue);
cut at the total, every later row stayed ``k`` frames off the grid an uninterrupted run's rows lie on. Now the
collector's first batch completes the pending steps to a whole batch, trained on at the grid frame.
"""

from __future__ import annotations

import shutil

import pytest
from _compare import assert_same
from _runs import checkpoint_contents, train
from test_pending_episodes import kill_with_pending_episode

from pe_rlhf.runtime.checkpoint import find_checkpoint
from pe_rlhf.runtime.journal import BatchJournal

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


def test_a_resume_from_a_pending_batch_ends_at_total_frames_with_its_rows_on_the_grid(tmp_path):
    killed = tmp_path / "killed"
    start, end = kill_with_pending_episode(killed, 125)
    assert start % 25 == 0 and start < end <= start + 25
    pending = BatchJournal(killed / "checkpoints" / "journal").pending_at(start)
    total = start + 55  # past the grid by 5, so the last batch is cut
    final = train(killed, f"collector.total_frames={total}", resume=True)
    assert final["training"]["frames"] == total
    assert find_checkpoint(killed / "checkpoints").name == f"ckpt_{total:09d}"
    rows = [int(float(line.split(",")[0])) for line in (killed / "metrics.csv").read_text().splitlines()[1:]]
    assert rows == [*range(25, start + 51, 25), total]  # an uninterrupted run's rows, then the cut at the total
    replay = checkpoint_contents(killed / "checkpoints" / f"ckpt_{total:09d}")["replay"]
    assert len(replay) == total
    for key in ("observation", "action", ("next", "observation"), ("next", "done")):  # the pending steps first
        assert_same(pending.batch[key], replay[start:end][key], f"{key} of frames {start}-{end}")


def test_a_pending_file_that_holds_a_whole_batch_is_trained_on_alone(tmp_path, monkeypatch):
    """An episode that ended on the batch's last step, killed before the batch was journaled: the pending file is
    the whole batch (frames 100-125 here, made from the journal file of that batch), trained on by itself and
    followed by whole batches; before, it was joined to the collector's first batch (one 50-frame row at 150)."""
    monkeypatch.setattr(BatchJournal, "prune", lambda self, frame: None)  # keep the batch files the checkpoints hold
    run = tmp_path / "run"
    train(run, "collector.total_frames=125")
    monkeypatch.undo()
    journal = BatchJournal(run / "checkpoints" / "journal")
    [path] = [path for end, path in journal.files() if end == 125]
    entry = journal.read(path)
    path.unlink()
    journal.write_pending(entry.batch, entry.start, entry.state)  # the killed run's state: pending, not journaled
    shutil.rmtree(run / "checkpoints" / "ckpt_000000125")  # the run was killed before it finished: ckpt_100 is
    (run / "checkpoints" / "latest").unlink()  # its newest
    final = train(run, "collector.total_frames=150", resume=True)
    assert final["training"]["frames"] == 150
    rows = [int(float(line.split(",")[0])) for line in (run / "metrics.csv").read_text().splitlines()[1:]]
    assert rows == [25, 50, 75, 100, 125, 150]
