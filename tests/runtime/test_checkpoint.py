"""Tests of ``pe_rlhf.runtime.checkpoint``: exact resume, pruning, crash/corruption handling, safety.

The round trip trains a small ``PERLHFLoss`` (3 Adam optimizers, SoftUpdate targets) from a
``TensorDictReplayBuffer``, saves, keeps training, then loads into freshly built objects and checks
that the continuation is bit-identical. Failures are injected by monkeypatching the module's single
file-writing helper (``pe_rlhf.durable.write_bytes``) or the buffer's ``dumps``.
"""

from __future__ import annotations

import copy
import errno
import json
import pickle
import random
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import SoftUpdate

from _compare import assert_same
from pe_rlhf.modules.networks import make_actor, make_qvalue
from pe_rlhf.objectives.perlhf import PERLHFLoss, make_transitions
from pe_rlhf import durable
from pe_rlhf.runtime import checkpoint as ck
from pe_rlhf.runtime.checkpoint import (CheckpointError, capture_rng, find_checkpoint, list_checkpoints,
                                         load_checkpoint, restore_rng, save_checkpoint)

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")

OBS_DIM, ACTION_DIM, HIDDEN, BATCH = 10, 2, (16, 16), 16
LOSS_KEYS = ("loss_qvalue", "loss_intervention_qvalue", "loss_actor", "loss_alpha")


# --------------------------------------------------------------------------- helpers


def transitions(n: int, seed: int) -> TensorDict:
    """Transitions with every key ``PERLHFLoss`` reads (see its docstring)."""
    g = torch.Generator().manual_seed(seed)
    intervention = torch.rand(n, 1, generator=g) < 0.4
    agent = torch.rand(n, ACTION_DIM, generator=g) * 2 - 1
    behavior = torch.where(intervention, torch.rand(n, ACTION_DIM, generator=g) * 2 - 1, agent)
    terminated = torch.rand(n, 1, generator=g) < 0.1
    return make_transitions(torch.randn(n, OBS_DIM, generator=g), torch.randn(n, OBS_DIM, generator=g),
                            agent, behavior, intervention, intervention.clone(), terminated)


class Run:
    """The objects a training run checkpoints."""

    def __init__(self, seed: int, hidden=HIDDEN):
        torch.manual_seed(seed)
        self.loss = PERLHFLoss(make_actor(OBS_DIM, ACTION_DIM, hidden), make_qvalue(OBS_DIM, ACTION_DIM, hidden),
                               make_qvalue(OBS_DIM, ACTION_DIM, hidden))
        self.updater = SoftUpdate(self.loss, tau=0.1)
        self.optimizers = {
            "actor": torch.optim.Adam(self.loss.actor_network_params.parameters(), lr=1e-3),
            "critic": torch.optim.Adam([*self.loss.qvalue_network_params.parameters(),
                                        *self.loss.intervention_qvalue_network_params.parameters()], lr=1e-3),
            "alpha": torch.optim.Adam([self.loss.log_alpha], lr=1e-2),
        }
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=BATCH)

    def update(self) -> TensorDict:
        out = self.loss(self.buffer.sample())
        for opt in self.optimizers.values():
            opt.zero_grad()
        sum(out[k] for k in LOSS_KEYS).backward()
        for opt in self.optimizers.values():
            opt.step()
        self.updater.step()
        return out.detach()

    def save(self, directory, step: int, state: dict | None = None, **kw) -> Path:
        return save_checkpoint(directory, step=step, modules={"loss": self.loss}, optimizers=self.optimizers,
                               replay_buffers={"online": self.buffer}, state=state or {"frames": step}, **kw)

    def load(self, directory, **kw) -> dict:
        return load_checkpoint(directory, modules={"loss": self.loss}, optimizers=self.optimizers,
                               replay_buffers={"online": self.buffer}, **kw)


def snapshot(run: Run) -> dict:
    return copy.deepcopy({"loss": run.loss.state_dict(),
                          "optimizers": {k: o.state_dict() for k, o in run.optimizers.items()},
                          "buffer": run.buffer[:].to_dict() if len(run.buffer) else None,
                          "len": len(run.buffer)})


@pytest.fixture
def trained() -> Run:
    run = Run(seed=0)
    run.buffer.extend(transitions(60, seed=1))
    for _ in range(3):
        run.update()
    return run


def rewrite_marker_entry(ckpt: Path, rel: str) -> None:
    """Make ``COMPLETE`` agree with ``rel``'s current bytes (an attacker or a bug that also fixes the marker)."""
    marker = json.loads((ckpt / "COMPLETE").read_text())
    entry = ck._manifest_entry(ckpt / rel)
    marker["files"][rel] = entry
    if rel == "tensors.pt":
        marker["sha256"] = entry["sha256"]
    (ckpt / "COMPLETE").write_text(json.dumps(marker))


class Evil:
    """Unpickling this creates ``path`` (a stand-in for arbitrary code)."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return open, (self.path, "w")


# --------------------------------------------------------------------------- round trip


def test_round_trip_is_exact_and_resumes_bit_identically(tmp_path, trained):
    state = {
        "frames": 1234, "updates": 3, "episodes": 7,
        "intervention": {"total_steps": 1234,
                         "mentor": {"controlled_steps": 5, "rng": np.random.default_rng(7).bit_generator.state,
                                    "queue": [[0.5, -0.25]]}},
        "schedule": {"last_fit": None},
        "config": {"lr": 1e-3, "hidden": [16, 16], "name": "pe-rlhf"},
        "numpy_scalar": np.int64(3),
    }
    path = trained.save(tmp_path, step=3, state=state)
    assert path == tmp_path / "ckpt_000000003"
    assert sorted(p.name for p in path.iterdir()) == ["COMPLETE", "buffer_online", "rng.pt", "state.json",
                                                      "tensors.pt"]
    assert (tmp_path / "latest").read_text().strip() == path.name
    torch.load(path / "tensors.pt", weights_only=True)  # the format promise
    torch.load(path / "rng.pt", weights_only=True)

    saved = snapshot(trained)
    continued = [trained.update() for _ in range(2)]
    draws = (np.random.rand(), random.random(), torch.rand(3))
    final = trained.loss.state_dict()

    fresh = Run(seed=123)  # other weights, empty buffer, fresh optimizers
    assert not torch.equal(fresh.loss.state_dict()["qvalue_network_params.module.mlp.0.weight"],
                           saved["loss"]["qvalue_network_params.module.mlp.0.weight"])
    loaded = fresh.load(tmp_path)
    expected_state = json.loads(json.dumps({**state, "numpy_scalar": 3}))
    assert loaded == {**expected_state, "step": 3}
    assert loaded["intervention"]["mentor"]["rng"] == np.random.default_rng(7).bit_generator.state
    restored = snapshot(fresh)
    # parameters, targets, log_alpha, target_entropy; Adam moments and steps; buffer contents
    assert_same(saved, restored)
    assert any(k.startswith("target_qvalue") for k in restored["loss"])

    resumed = [fresh.update() for _ in range(2)]
    for a, b in zip(continued, resumed):
        for k in LOSS_KEYS:
            assert torch.equal(a[k], b[k]), k
    assert (np.random.rand(), random.random()) == draws[:2]
    assert torch.equal(torch.rand(3), draws[2])
    assert_same(final, fresh.loss.state_dict())


def test_capture_restore_rng():
    state = capture_rng()
    a = (torch.rand(4), np.random.rand(3), random.random(), np.random.randn())
    restore_rng(state)
    b = (torch.rand(4), np.random.rand(3), random.random(), np.random.randn())
    assert torch.equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2:] == b[2:]
    json.dumps({k: v for k, v in state.items() if k in ("numpy", "python")})  # plain ints/floats/lists
    with pytest.raises(ValueError, match="malformed RNG state"):
        restore_rng({**state, "numpy": {**state["numpy"], "key": [1, 2, 3]}})


def test_empty_buffer_and_strict_names(tmp_path, trained):
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    save_checkpoint(tmp_path, step=1, modules={"loss": trained.loss}, optimizers=trained.optimizers,
                    replay_buffers={"online": trained.buffer, "demo": empty}, state={})
    fresh = Run(seed=5)
    other = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    other.extend(transitions(3, seed=0))
    with pytest.raises(ValueError, match="replay buffers mismatch"):
        fresh.load(tmp_path)  # "demo" not given
    with pytest.raises(ValueError, match=r"optimizers mismatch: not in the checkpoint \['extra'\]"):
        load_checkpoint(tmp_path, modules={"loss": fresh.loss}, optimizers={"actor": fresh.optimizers["actor"],
                        "extra": fresh.optimizers["alpha"]}, replay_buffers={"online": fresh.buffer, "demo": other})
    state = load_checkpoint(tmp_path, modules={"loss": fresh.loss}, optimizers=fresh.optimizers,
                            replay_buffers={"online": fresh.buffer, "demo": other})
    assert state == {"step": 1} and len(other) == 0 and len(fresh.buffer) == 60
    # strict=False: a subset (evaluation loads only the modules)
    evaluation = Run(seed=9)
    load_checkpoint(tmp_path, modules={"loss": evaluation.loss}, optimizers={}, strict=False)
    assert_same(trained.loss.state_dict(), evaluation.loss.state_dict())


def test_module_mismatch_names_module_and_key(tmp_path, trained):
    trained.save(tmp_path, step=1)
    bigger = Run(seed=0, hidden=(32, 32))
    with pytest.raises(ValueError, match=r"module 'loss' key '[^']*weight'.*shape") as info:
        bigger.load(tmp_path)
    assert not isinstance(info.value, CheckpointError)


def test_state_must_be_json(tmp_path, trained):
    with pytest.raises(TypeError, match=r"state\['mentor'\]\['rng'\] is a Generator"):
        trained.save(tmp_path, step=1, state={"mentor": {"rng": np.random.default_rng()}})
    with pytest.raises(TypeError, match="non-string key"):
        trained.save(tmp_path, step=1, state={"counts": {1: 2}})
    with pytest.raises(ValueError, match="differs from step"):
        trained.save(tmp_path, step=1, state={"step": 2})
    assert list_checkpoints(tmp_path) == [] and not (tmp_path / "latest").exists()


# --------------------------------------------------------------------------- pruning, temp dirs, re-save


def test_keep_prunes_old_and_latest_points_to_newest(tmp_path, trained):
    for step in (10, 20, 30):
        trained.save(tmp_path, step=step, keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000020", "ckpt_000000030"]
    assert (tmp_path / "latest").read_text() == "ckpt_000000030\n"
    assert fresh_step(tmp_path) == 30
    trained.save(tmp_path, step=40, keep=1)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000040"]
    with pytest.raises(ValueError, match="keep"):
        trained.save(tmp_path, step=50, keep=0)


def fresh_step(directory) -> int:
    return Run(seed=1).load(directory)["step"]


def test_half_written_temp_dir_is_ignored_and_cleaned(tmp_path, trained):
    trained.save(tmp_path, step=1)
    tmp = tmp_path / ".tmp-ckpt_000000002-99999"  # a writer killed half-way
    tmp.mkdir()
    (tmp / "tensors.pt").write_bytes(b"PK\x03\x04 half")
    assert find_checkpoint(tmp_path) == tmp_path / "ckpt_000000001"
    assert fresh_step(tmp_path) == 1
    trained.save(tmp_path, step=2)
    assert not tmp.exists() and fresh_step(tmp_path) == 2


def test_resaving_a_step_replaces_it(tmp_path, trained):
    trained.save(tmp_path, step=5, state={"v": 1})
    trained.save(tmp_path, step=5, state={"v": 2})
    assert Run(seed=1).load(tmp_path) == {"v": 2, "step": 5}
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == ["ckpt_000000005"]


# --------------------------------------------------------------------------- corruption


@pytest.mark.parametrize("rel", ["tensors.pt", "rng.pt", "state.json", "buffer_online/storage/observation.memmap.zlib"])
def test_truncated_file_raises_checkpoint_error_naming_it(tmp_path, trained, rel):
    ckpt = trained.save(tmp_path, step=1)
    path = ckpt / rel
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=rf"{rel}.*truncated or corrupt"):
        Run(seed=1).load(tmp_path)


@pytest.mark.parametrize("rel", ["tensors.pt", "rng.pt"])
def test_truncated_file_with_matching_marker_still_checkpoint_error(tmp_path, trained, rel):
    """Even if the checksum agrees, an unreadable file gives a CheckpointError, not a torch trace."""
    ckpt = trained.save(tmp_path, step=1)
    path = ckpt / rel
    path.write_bytes(path.read_bytes()[:100])
    rewrite_marker_entry(ckpt, rel)
    with pytest.raises(CheckpointError, match=rf"unreadable checkpoint file .*{rel}") as info:
        Run(seed=1).load(tmp_path)
    assert info.value.__cause__ is None and info.value.__suppress_context__


def test_corrupt_marker_raises(tmp_path, trained):
    ckpt = trained.save(tmp_path, step=1)
    (ckpt / "COMPLETE").write_bytes((ckpt / "COMPLETE").read_bytes()[:40])
    with pytest.raises(CheckpointError, match="corrupt checkpoint marker .*COMPLETE"):
        Run(seed=1).load(tmp_path)


def test_missing_complete_falls_back_to_previous(tmp_path, trained):
    trained.save(tmp_path, step=1, state={"frames": 1})
    ckpt2 = trained.save(tmp_path, step=2, state={"frames": 2})
    (ckpt2 / "COMPLETE").unlink()
    with pytest.warns(UserWarning, match="not a complete checkpoint"):
        state = Run(seed=1).load(tmp_path)
    assert state == {"frames": 1, "step": 1}
    (tmp_path / "latest").unlink()  # no pointer at all: newest complete one
    assert Run(seed=1).load(tmp_path)["step"] == 1
    (tmp_path / "ckpt_000000001" / "COMPLETE").unlink()
    with pytest.raises(FileNotFoundError, match="no complete checkpoint"):
        Run(seed=1).load(tmp_path)


def test_explicit_checkpoint_directory_loads_that_one(tmp_path, trained):
    trained.save(tmp_path, step=1, state={"frames": 1})
    trained.save(tmp_path, step=2, state={"frames": 2})
    with pytest.warns(UserWarning, match="larger steps"):
        assert Run(seed=1).load(tmp_path / "ckpt_000000001")["frames"] == 1


# --------------------------------------------------------------------------- unsafe payloads


@pytest.mark.parametrize("target", ["tensors.pt", "rng.pt", "buffer_online/prefetch.pkl", "buffer_online/transform.t"])
def test_malicious_pickle_is_refused(tmp_path, trained, target):
    ckpt = trained.save(tmp_path, step=1)
    sentinel = tmp_path / "pwned"
    # sanity: the payload really runs code when unpickled without protection
    control = tmp_path / "control"
    pickle.loads(pickle.dumps(Evil(control))).close()
    assert control.exists()

    path = ckpt / target
    if target.endswith(".pkl"):
        path.write_bytes(pickle.dumps({"version": 1, "capacity": 0, "queue": (Evil(sentinel),)}))
    else:
        torch.save({"modules": Evil(sentinel)}, path)
    rewrite_marker_entry(ckpt, target)  # the checksums agree: only the loader's caution protects us
    fresh = Run(seed=1)
    before = snapshot(fresh)
    with pytest.raises(CheckpointError, match=rf"{Path(target).name}") as info:
        fresh.load(tmp_path)
    assert not sentinel.exists()
    assert info.value.__cause__ is None
    assert_same(before, snapshot(fresh))  # nothing was restored from a refused checkpoint


def test_unlisted_buffer_file_is_refused(tmp_path, trained):
    ckpt = trained.save(tmp_path, step=1)
    (ckpt / "buffer_online" / "extra.pkl").write_bytes(pickle.dumps(1))
    with pytest.raises(CheckpointError, match="unexpected file .*extra.pkl"):
        Run(seed=1).load(tmp_path)


# --------------------------------------------------------------------------- disk full


@pytest.mark.parametrize("failing", ["tensors.pt", "rng.pt", "buffer", "COMPLETE", "latest"])
def test_disk_full_keeps_previous_checkpoint(tmp_path, trained, monkeypatch, failing):
    trained.save(tmp_path, step=1, state={"frames": 1})
    at_save = snapshot(trained)
    trained.update()

    real_write = durable.write_bytes

    def write(path: Path, data: bytes) -> None:
        if path.name == failing or (failing == "latest" and path.name.startswith(".latest.tmp")):
            real_write(path, data[: len(data) // 2])  # half the bytes land, then the disk is full
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real_write(path, data)

    def dumps(path):
        Path(path).mkdir()
        (Path(path) / "partial.memmap").write_bytes(b"\0" * 10)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(durable, "write_bytes", write)
    if failing == "buffer":
        monkeypatch.setattr(trained.buffer, "dumps", dumps)
    with pytest.raises(OSError, match=r"could not write checkpoint step 2 .*No space left.*ckpt_000000001 is intact") \
            as info:
        trained.save(tmp_path, step=2, state={"frames": 2})
    assert info.value.errno == errno.ENOSPC
    monkeypatch.undo()

    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == ["ckpt_000000001"]
    assert (tmp_path / "latest").read_text() == "ckpt_000000001\n"
    fresh = Run(seed=7)
    assert fresh.load(tmp_path) == {"frames": 1, "step": 1}
    assert_same(at_save, snapshot(fresh))
    # the disk has room again: the next save works and prunes as usual
    trained.save(tmp_path, step=3, keep=1)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000003"]


def test_refusal_message_is_short_and_names_the_file(tmp_path, trained):
    ckpt = trained.save(tmp_path, step=1)
    torch.save(Evil(tmp_path / "x"), ckpt / "tensors.pt")
    rewrite_marker_entry(ckpt, "tensors.pt")
    with pytest.raises(CheckpointError) as info:
        Run(seed=1).load(tmp_path)
    message = str(info.value)
    assert "tensors.pt" in message and "Unsupported global" in message and len(message) < 600


def test_failed_resave_of_a_step_keeps_the_old_one(tmp_path, trained, monkeypatch):
    trained.save(tmp_path, step=5, state={"v": 1})
    real_write = durable.write_bytes

    def write(path: Path, data: bytes) -> None:
        if path.name.startswith(".latest.tmp"):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real_write(path, data)

    monkeypatch.setattr(durable, "write_bytes", write)
    with pytest.raises(OSError, match="ckpt_000000005 is intact"):
        trained.save(tmp_path, step=5, state={"v": 2})
    monkeypatch.undo()
    assert Run(seed=1).load(tmp_path) == {"v": 1, "step": 5}
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == ["ckpt_000000005"]
