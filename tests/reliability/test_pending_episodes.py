"""Episodes that ended inside the batch being collected survive a SIGKILL (``PendingEpisodesJournal``).

The transform on a plain TorchRL env (Pendulum, episodes cut by ``StepCounter``): a pending file is
written exactly when an episode ends, holds what the collector's batch holds for those steps, loads
with ``weights_only=True``, and a damaged one is refused by name. Then a training child (episodes of
at most 20 steps, 25-frame batches) is killed while an episode that ended in the batch being
collected is only in its pending file; ``--resume`` must keep those steps: the replay buffer equals
an uninterrupted run's up to the episode's end, and the counters agree with that run's.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
import torch
from _compare import assert_same
from _runs import UNIFORM_REPLAY, checkpoint_contents, kill_rng, start_training, train
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import RandomPolicy

from pe_rlhf.runtime.checkpoint import CheckpointError, find_checkpoint
from pe_rlhf.runtime.episode_journal import PendingEpisodesJournal
from pe_rlhf.runtime.journal import BatchJournal
from pe_rlhf.algorithms.proxy_q.steps import batch_metrics

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]

HORIZON = "env.horizon=20"  # every 25-frame batch holds an episode end
# the rows in collection order (replay[frame]): one uniform buffer, not the default's takeover rows apart
ROWS = (HORIZON, UNIFORM_REPLAY)


def pendulum_batches(directory: Path, max_steps: int, frames_per_batch: int, batches: int):
    """``(journal, [(batch, (start, end) of the pending files after it), ...])`` for a journaled
    Pendulum collector whose episodes last ``max_steps`` steps."""
    torch.manual_seed(0)
    env = TransformedEnv(GymEnv("Pendulum-v1"), StepCounter(max_steps))
    journal = BatchJournal(directory)
    env.append_transform(PendingEpisodesJournal(journal, frames_per_batch, lambda: {"mentor": "state"}))
    env.set_seed(0)
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=frames_per_batch,
                          total_frames=frames_per_batch * batches)
    out = [(batch.clone(), [(start, end) for start, end, _ in journal.pending_files()]) for batch in collector]
    collector.shutdown()
    return journal, out


def test_pending_file_is_written_at_each_episode_end_with_the_batch_steps_so_far(tmp_path):
    journal, out = pendulum_batches(tmp_path, max_steps=6, frames_per_batch=4, batches=3)
    (_, after0), (b1, after1), (b2, after2) = out
    assert after0 == []  # frames 0-3: no episode ended, nothing written
    assert after1 == [(4, 6)]  # the episode ended at frame 5
    assert after2 == [(4, 6), (8, 12)]  # the next one at frame 11; the trainer deletes (4, 6), not the transform
    first, second = (journal.read(path) for *_, path in journal.pending_files())
    assert (first.start, first.end, second.start, second.end) == (4, 6, 8, 12)
    assert_same(b1[:2], first.batch, "frames 4-5")  # what the collector's batch holds, keys and values
    assert_same(b2, second.batch, "frames 8-11")
    assert first.state == {"mentor": "state"} and isinstance(first.rng["torch"], torch.Tensor)
    raw = torch.load(second.path, weights_only=True)
    assert raw["start"] == 8 and raw["batch_size"] == [4]
    assert journal.pending_at(8).end == 12  # the one continuing frame 8; the older one is stale ...
    assert [start for start, *_ in journal.pending_files()] == [8]  # ... and deleted
    journal.discard_pending(8)  # the batch at 8 is journaled whole
    assert journal.pending_files() == []


def test_a_later_episode_end_in_the_same_batch_replaces_the_pending_file(tmp_path):
    journal, [(batch, pending)] = pendulum_batches(tmp_path, max_steps=3, frames_per_batch=8, batches=1)
    assert pending == [(0, 6)]  # episodes ended at frames 2 and 5
    assert_same(batch[:6], journal.read(journal.pending_files()[0][2]).batch, "frames 0-5")


@pytest.mark.parametrize("damage", ["flip", "truncate"])
def test_damaged_pending_file_is_refused_by_name(tmp_path, damage):
    journal, _ = pendulum_batches(tmp_path, max_steps=3, frames_per_batch=8, batches=1)
    path = journal.pending_files()[0][2]
    data = bytearray(path.read_bytes())
    if damage == "flip":
        data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data if damage == "flip" else data[: len(data) // 2]))
    with pytest.raises(CheckpointError, match=r"journal file .*pending_000000000_000000006.* is corrupt or truncated"):
        journal.read(path)
    with pytest.warns(UserWarning, match=r"pending_000000000_000000006.*corrupt.*the steps it held are lost"):
        assert journal.pending_at(0) is None
    assert journal.pending_files() == []


def kill_with_pending_episode(out: Path, after: int, timeout: float = 240.0) -> tuple[int, int]:
    """Train in a child and SIGKILL it while the batch it is collecting starts at or after frame
    ``after``, holds a finished episode (a pending file) and is not journaled yet. The child is
    stopped (SIGSTOP) to check that on a still disk. Returns the pending file's ``(start, end)``."""
    proc = start_training(out, "collector.total_frames=400", *ROWS)
    journal_dir = out / "checkpoints" / "journal"
    deadline = time.time() + timeout
    try:
        while time.time() < deadline and proc.poll() is None:
            if journal_dir.is_dir():
                journal = BatchJournal(journal_dir)
                if any(start >= after for start, *_ in journal.pending_files()):
                    os.kill(proc.pid, signal.SIGSTOP)
                    pending = journal.pending_files()
                    ckpt = find_checkpoint(journal_dir.parent)
                    journaled = max((end for end, _ in journal.files()), default=int(ckpt.name[5:]) if ckpt else 0)
                    if pending and pending[-1][0] == journaled:
                        proc.send_signal(signal.SIGKILL)
                        proc.wait()
                        return pending[-1][:2]
                    os.kill(proc.pid, signal.SIGCONT)  # its batch got journaled meanwhile: wait for the next
            time.sleep(0.005)
        log = (out.parent / f"{out.name}.log").read_text()[-2000:]
        pytest.fail(f"the child never held a pending episode after frame {after} (rc {proc.poll()}):\n{log}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sigkill_keeps_the_episodes_that_ended_in_the_batch_being_collected(tmp_path):
    after = kill_rng("training").choice([125, 150, 175])  # past the checkpoint at 100: journal replay too
    killed = tmp_path / "killed"
    start, end = kill_with_pending_episode(killed, after)
    ckpts = killed / "checkpoints"
    saved = int(find_checkpoint(ckpts).name[5:])
    assert [e for e, _ in BatchJournal(ckpts / "journal").files()] == list(range(saved + 25, start + 1, 25))
    assert saved >= 100 and start % 25 == 0 and start < end <= start + 25, (after, saved, start, end)

    final = train(killed, f"collector.total_frames={end}", resume=True)
    assert final["training"]["frames"] == end  # the journal's batches, then the pending episode's steps
    train(tmp_path / "uninterrupted", f"collector.total_frames={start + 25}", *ROWS)
    resumed = checkpoint_contents(ckpts / f"ckpt_{end:09d}")
    uninterrupted = checkpoint_contents(tmp_path / "uninterrupted" / "checkpoints" / f"ckpt_{start + 25:09d}")
    assert len(resumed["replay"]) == end
    assert_same(uninterrupted["replay"][:end], resumed["replay"], f"killed in the batch at {start}")
    assert_same(uninterrupted["warmup"], resumed["warmup"], "warm-up buffer")
    assert bool(resumed["replay"][end - 1]["next", "done"])  # kept up to the episode's end, no further

    # The counters: the resumed run's at ``end`` plus the uninterrupted run's last steps make its total.
    tail = batch_metrics(uninterrupted["replay"][end:])
    counters, expected = resumed["state"]["counters"], dict(uninterrupted["state"]["counters"])
    for key, metric in (("frames", "steps"), ("online_frames", "steps"), ("episodes", "episodes"),
                        ("successes", "successes"), ("safety_violations", "safety_violations"),
                        ("sim_errors", "sim_errors"), ("takeover_steps", "takeover_steps"),
                        ("takeover_starts", "takeover_starts"), ("mentor_chosen_steps", "mentor_chosen_steps")):
        assert counters[key] + tail[metric] == expected[key], key
    assert resumed["state"]["transform_steps"] == end

    final = train(killed, f"collector.total_frames={end + 25}", resume=True)  # collecting goes on from there
    assert final["training"]["frames"] == end + 25
    rows = [int(float(line.split(",")[0])) for line in (killed / "metrics.csv").read_text().splitlines()[1:]]
    assert rows == sorted({*range(25, start + 26, 25), end, end + 25})  # no gap, no repeat; back on the grid
    assert not list((ckpts / "journal").iterdir())


def test_a_collection_that_completes_a_pending_batch_journals_it_on_the_grid(tmp_path):
    """``restart(start, steps)``: the killed run's pending steps of the batch at ``start`` come first; the collector's
    first batch tops them up to the grid (:func:`batches_on_grid`), and an episode that ends meanwhile is written
    with them, so a second kill keeps both."""
    from pe_rlhf.algorithms.proxy_q.builders import batches_on_grid

    torch.manual_seed(0)
    env = TransformedEnv(GymEnv("Pendulum-v1"), StepCounter(2))
    journal = BatchJournal(tmp_path)
    pending = PendingEpisodesJournal(journal, 4)
    env.append_transform(pending)
    env.set_seed(0)
    head = pendulum_batches(tmp_path / "killed", max_steps=2, frames_per_batch=4, batches=2)[1][1][0][:2]
    pending.restart(4, head)  # frames 4-5 were the killed run's; collection goes on at 6
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=4, total_frames=6)
    batches = [batch.clone() for batch in batches_on_grid(collector, 6)]
    collector.shutdown()
    assert [b.numel() for b in batches] == [2, 4]  # frames 6-7, then 8-11
    assert [(start, end) for start, end, _ in journal.pending_files()] == [(4, 8), (8, 12)]  # (8, 10) replaced
    first = journal.read(journal.pending_files()[0][2]).batch
    assert_same(head, first[:2], "the killed run's steps")
    assert_same(batches[0], first[2:], "the top-up's steps")


def test_a_collection_that_starts_off_the_grid_returns_to_it(tmp_path):
    """A resume from a checkpoint cut at ``collector.total_frames`` (frame 6 of 4-frame batches): the first batch
    is frames 6-7, and the pending files of the next batch start at frame 8."""
    from pe_rlhf.algorithms.proxy_q.builders import batches_on_grid

    torch.manual_seed(0)
    env = TransformedEnv(GymEnv("Pendulum-v1"), StepCounter(2))
    journal = BatchJournal(tmp_path)
    env.append_transform(PendingEpisodesJournal(journal, 4, start_frames=6))
    env.set_seed(0)
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=4, total_frames=6)
    assert [batch.numel() for batch in batches_on_grid(collector, 6)] == [2, 4]  # frames 6-7, then 8-11
    collector.shutdown()
    assert [(start, end) for start, end, _ in journal.pending_files()] == [(6, 8), (8, 12)]  # ends at 7, 9, 11
