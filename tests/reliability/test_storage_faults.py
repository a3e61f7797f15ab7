"""Checkpoint writes interrupted by SIGKILL or a full disk, truncated or corrupt files: the previous
checkpoint stays valid, damage is reported with the file named, and nothing collected is lost.

(``tests/runtime/test_checkpoint.py`` injects the same faults into each file of one ``save_checkpoint``;
these tests do it to a real writer process and to a training run.)"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from _runs import ROOT, kill_rng, train
from _scripts import SCRIPT_ENV
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from pe_rlhf import durable
from pe_rlhf.runtime import checkpoint as ck
from pe_rlhf.runtime.checkpoint import CheckpointError, find_checkpoint, list_checkpoints, load_checkpoint
from pe_rlhf.runtime.journal import BatchJournal

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]

WRITER = """
import sys, torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from pe_rlhf.runtime.checkpoint import save_checkpoint
net = torch.nn.Linear(250, 256)
buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(20000))
for step in range(1, 10000):
    buffer.extend(TensorDict({"observation": torch.full((1000, 250), float(step))}, batch_size=[1000]))
    save_checkpoint(sys.argv[1], step=step, modules={"net": net}, optimizers={}, replay_buffers={"b": buffer},
                    state={"rows": len(buffer)}, keep=2)
"""


def fresh_buffer() -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=LazyTensorStorage(20000))


def test_sigkill_during_checkpoint_writes_leaves_a_valid_checkpoint(tmp_path):
    env = {**os.environ, "PYTHONPATH": SCRIPT_ENV["PYTHONPATH"], "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 120
        while not (tmp_path / "ckpt_000000002" / "COMPLETE").exists():
            assert proc.poll() is None and time.time() < deadline, proc.stderr.read().decode()[-2000:]
            time.sleep(0.01)
        time.sleep(kill_rng("checkpoint writer").uniform(0.0, 1.0))  # somewhere inside a later write
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    ckpt = find_checkpoint(tmp_path)
    step = int(ckpt.name.split("_")[1])
    buffer = fresh_buffer()
    state = load_checkpoint(tmp_path, modules={"net": torch.nn.Linear(250, 256)}, optimizers={},
                            replay_buffers={"b": buffer})
    assert state["step"] == step >= 2 and state["rows"] == len(buffer) == 1000 * step
    assert torch.equal(buffer[:]["observation"][-1], torch.full((250,), float(step)))
    ck.save_checkpoint(tmp_path, step=step + 1, modules={}, optimizers={}, keep=1)  # the next save tidies up
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]


def test_disk_full_during_a_run_keeps_the_last_checkpoint_and_the_journal_recovers_the_rest(tmp_path, monkeypatch):
    """The disk fills up as the checkpoint at frame 100 is written: the run stops with a clear error,
    the checkpoint at 50 stays loadable, and once there is room ``--resume`` gets frames 51-100
    back from the journal written before the disk filled."""
    real_write = durable.write_bytes

    def write(path: Path, data: bytes) -> None:
        if "ckpt_000000100" in str(path):
            real_write(path, data[: len(data) // 2])  # half the bytes land, then the disk is full
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real_write(path, data)

    monkeypatch.setattr(durable, "write_bytes", write)
    out = tmp_path / "run"
    with pytest.raises(OSError, match=r"could not write checkpoint step 100 .*No space left on device.*"
                                      r"ckpt_000000050 is intact") as info:
        train(out, "collector.total_frames=150", "checkpoint.every_frames=50")
    assert info.value.errno == errno.ENOSPC
    monkeypatch.undo()
    ckpts = out / "checkpoints"
    assert [p.name for p in list_checkpoints(ckpts)] == ["ckpt_000000050"]
    assert [end for end, _ in BatchJournal(ckpts / "journal").files()] == [75, 100]
    final = train(out, "collector.total_frames=100", resume=True)
    assert final["training"]["frames"] == 100  # the journal's two batches, not collected again


def test_journal_write_on_a_full_disk_is_a_clear_error(tmp_path, monkeypatch):
    journal = BatchJournal(tmp_path)

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(durable, "write_bytes", full)
    with pytest.raises(OSError, match=r"could not journal frames 10-14 to .*batch_000000014.*No space left"):
        journal.write(TensorDict({"x": torch.zeros(4)}, batch_size=[4]), start=10)
    assert not list(tmp_path.iterdir())  # no partial file left behind


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_corrupt_journal_file_is_named_and_replay_stops_before_it(tmp_path, damage):
    journal = BatchJournal(tmp_path)
    paths = [journal.write(TensorDict({"x": torch.full((5, 1), float(i))}, batch_size=[5]), start=5 * i)
             for i in range(3)]
    data = bytearray(paths[1].read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 2] ^= 0xFF
    paths[1].write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=r"journal file .*batch_000000010.* is corrupt or truncated.*up to frame 5"):
        entries = journal.entries_after(0)
    assert [e.end for e in entries] == [5]
    assert [end for end, _ in journal.files()] == [5]  # the frames after it are collected again


@pytest.mark.parametrize("rel", ["tensors.pt", "state.json", "buffer_b/storage/observation.memmap.zlib"])
def test_truncated_checkpoint_is_a_clear_error_not_a_torch_trace(tmp_path, rel):
    buffer = fresh_buffer()
    buffer.extend(TensorDict({"observation": torch.zeros(10, 250)}, batch_size=[10]))
    ckpt = ck.save_checkpoint(tmp_path, step=1, modules={"net": torch.nn.Linear(2, 2)}, optimizers={},
                              replay_buffers={"b": buffer})
    path = ckpt / rel
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=rf"{rel}.* is truncated or corrupt") as info:
        load_checkpoint(tmp_path, modules={"net": torch.nn.Linear(2, 2)}, optimizers={},
                        replay_buffers={"b": fresh_buffer()})
    assert info.value.__cause__ is None and len(str(info.value)) < 400
