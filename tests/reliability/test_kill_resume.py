"""SIGKILL at a random step, then ``--resume``: nothing collected is lost and the bookkeeping agrees.

A child process trains (checkpoint every 100 frames, 25-frame batches) and is killed once its journal
holds a randomly chosen number of batches past the checkpoint at 100. The run is resumed in this
process up to the last journaled frame ``J``, and an uninterrupted run of the same config to ``J``
is the reference: replay buffers, counters, networks, optimisers and RNG states must be identical.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from _compare import assert_same
from _runs import checkpoint_contents, kill_rng, start_training, train

from pe_rlhf.runtime.journal import BatchJournal

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


def kill_when_journaled(out: Path, frames: int, timeout: float = 240.0, checkpoint_every: int = 100) -> None:
    proc = start_training(out, "collector.total_frames=300", f"checkpoint.every_frames={checkpoint_every}")
    journal = out / "checkpoints" / "journal"
    deadline = time.time() + timeout
    try:
        while time.time() < deadline and proc.poll() is None:
            if journal.is_dir() and any(end >= frames for end, _ in BatchJournal(journal).files()):
                proc.send_signal(signal.SIGKILL)
                proc.wait()
                return
            time.sleep(0.01)
        log = (out.parent / f"{out.name}.log").read_text()[-2000:]
        pytest.fail(f"the child never journaled frame {frames} (rc {proc.poll()}):\n{log}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sigkill_then_resume_loses_no_batch_and_matches_an_uninterrupted_run(tmp_path):
    target = kill_rng("training").choice([125, 150, 175])  # the kill lands somewhere after this batch
    killed = tmp_path / "killed"
    kill_when_journaled(killed, target)
    ckpts = killed / "checkpoints"
    journaled = [end for end, _ in BatchJournal(ckpts / "journal").files()]
    assert (ckpts / "ckpt_000000100" / "COMPLETE").is_file(), f"target {target}"
    last = max(journaled)
    assert last >= target and journaled == list(range(125, last + 1, 25)), (target, journaled)

    final = train(killed, f"collector.total_frames={last}", resume=True)
    assert final["training"]["frames"] == last  # every journaled batch is back, none collected twice
    reference = train(tmp_path / "uninterrupted", f"collector.total_frames={last}")
    assert reference["training"]["frames"] == last

    resumed = checkpoint_contents(ckpts / f"ckpt_{last:09d}")
    uninterrupted = checkpoint_contents(tmp_path / "uninterrupted" / "checkpoints" / f"ckpt_{last:09d}")
    assert len(resumed["replay"]) == last and len(resumed["warmup"]) == 50
    assert_same(uninterrupted, resumed, f"killed after frame {target}")
    rows = [line.split(",")[0] for line in (killed / "metrics.csv").read_text().splitlines()[1:]]
    assert [int(float(r)) for r in rows] == list(range(25, last + 1, 25))  # the curve: no gap, no repeat
    assert not BatchJournal(ckpts / "journal").files()  # the final checkpoint holds every batch now
    # an episode that ended in the batch being collected at the kill stays pending for a longer run
    assert all(start == last for start, *_ in BatchJournal(ckpts / "journal").pending_files())
