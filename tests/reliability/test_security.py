"""Files a user may receive from someone else never run code: every loader refuses a malicious pickle;
the package has no unsafe loading call; checkpoints do not unpickle even their own files; nothing
reaches the network (the suite's ``no_network`` guard, tested here), wandb defaults to offline."""

from __future__ import annotations

import ast
import hashlib
import io
import json
import pickle
import socket
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from pe_rlhf.runtime.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

SRC = Path(__file__).resolve().parents[2] / "src" / "pe_rlhf"


class Evil:
    """Unpickling this creates ``path`` (a stand-in for arbitrary code)."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return open, (self.path, "w")


def evil_bytes(sentinel: Path) -> bytes:
    buf = io.BytesIO()
    torch.save({"modules": Evil(sentinel)}, buf)
    return buf.getvalue()


def test_the_payload_really_runs_code_when_loaded_unsafely(tmp_path):
    torch.load(io.BytesIO(evil_bytes(tmp_path / "control")), weights_only=False).get("modules").close()
    assert (tmp_path / "control").exists()


def test_journal_refuses_a_malicious_batch(tmp_path):
    from pe_rlhf.runtime.journal import BatchJournal

    journal = BatchJournal(tmp_path / "journal")
    journal.write(TensorDict({"x": torch.zeros(4, 1)}, batch_size=[4]), start=0)
    data = evil_bytes(tmp_path / "pwned")  # named with its own sha256: only the loader's caution protects us
    (journal.directory / f"batch_{8:09d}-{hashlib.sha256(data).hexdigest()[:16]}.pt").write_bytes(data)
    with pytest.warns(UserWarning, match=r"unreadable journal file .*batch_000000008.*not plain tensor data"):
        entries = journal.entries_after(0)
    assert [e.end for e in entries] == [4] and not (tmp_path / "pwned").exists()
    assert [end for end, _ in journal.files()] == [4]  # the refused file is gone


def test_trained_actor_file_is_refused(tmp_path):
    from _runs import TINY

    from pe_rlhf.runtime.config import save_config
    from pe_rlhf.algorithms.proxy_q.config import load_config
    from pe_rlhf.algorithms.proxy_q.trained_policy import load_actor

    save_config(load_config(overrides=TINY), tmp_path / "config.yaml")
    (tmp_path / "actor.pt").write_bytes(evil_bytes(tmp_path / "pwned"))
    with pytest.raises(ValueError, match="refusing .*actor.pt: not plain tensor data"):
        load_actor(tmp_path)
    assert not (tmp_path / "pwned").exists()


def test_q_ensemble_file_is_refused(tmp_path):
    from pe_rlhf.modules import load_q_ensemble

    (tmp_path / "q.pt").write_bytes(evil_bytes(tmp_path / "pwned"))
    with pytest.raises(ValueError, match="q.pt"):
        load_q_ensemble(tmp_path / "q.pt")
    assert not (tmp_path / "pwned").exists()


def test_demonstration_chunk_is_refused(tmp_path):
    from pe_rlhf.envs import DrivingConfig
    from pe_rlhf.mentors.recording import DemonstrationRecorder, load_demonstrations

    config = DrivingConfig(horizon=20, min_blocks=2, max_blocks=2)
    with DemonstrationRecorder(tmp_path / "demo", config, mentor_name="professional") as rec:
        t = 3
        flags = {k: torch.zeros(t, 1, dtype=torch.bool) for k in ("done", "terminated", "truncated", "success",
                                                                    "crash_vehicle", "crash_object", "out_of_road")}
        floats = {k: torch.zeros(t, 1) for k in ("reward", "cost", "route_completion", "travel_distance", "velocity")}
        ints = {k: torch.zeros(t, 1, dtype=torch.int64) for k in ("overtakes", "scene_seed")}
        rec.write_episode(TensorDict({"observation": torch.zeros(t, 250), "action": torch.zeros(t, 2),
                                      "next": {"observation": torch.zeros(t, 250), **flags, **floats, **ints}},
                                     batch_size=[t]))
    data = evil_bytes(tmp_path / "pwned")
    (tmp_path / "demo" / "episodes" / "000000.pt").write_bytes(data)
    manifest = json.loads((tmp_path / "demo" / "manifest.jsonl").read_text())
    manifest.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())  # checksums agree
    (tmp_path / "demo" / "manifest.jsonl").write_text(json.dumps(manifest) + "\n")
    with pytest.raises(ValueError, match="unreadable episode chunk .*000000.pt"):
        load_demonstrations(tmp_path / "demo", config)
    assert not (tmp_path / "pwned").exists()


def _calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            name = ast.unparse(node.func)
            yield name, {k.arg: ast.unparse(k.value) for k in node.keywords}, node.lineno


def test_no_unsafe_loading_call_in_the_package():
    """Every ``torch.load`` passes ``weights_only=True``; nothing calls ``pickle.load(s)``, ``eval``,
    ``exec``, ``numpy.load(allow_pickle=True)`` or loads a memmap with ``allow_pickle=True``."""
    problems = []
    for path in sorted(SRC.rglob("*.py")):
        for name, kwargs, line in _calls(ast.parse(path.read_text())):
            where = f"{path.relative_to(SRC)}:{line} {name}"
            if name.endswith("torch.load") and kwargs.get("weights_only") != "True":
                problems.append(where)
            if name in ("pickle.load", "pickle.loads", "eval", "exec", "marshal.loads") or (
                    kwargs.get("allow_pickle") == "True"):
                problems.append(where)
    assert not problems, problems


def test_checkpointing_a_prefetching_buffer_unpickles_nothing(tmp_path, monkeypatch):
    """torchrl writes the prefetch queue as a pickle of sampled batches; the checkpoint replaces it
    without reading it (no ``pickle.load``), and the buffer loads back."""
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(50), batch_size=4, prefetch=2)
    buffer.extend(TensorDict({"x": torch.arange(20.0).unsqueeze(-1)}, batch_size=[20]))
    buffer.sample()  # fills the prefetch queue

    def refuse(*args, **kwargs):
        raise AssertionError("a checkpoint save must not unpickle anything")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    with pytest.warns(UserWarning, match="prefetched batches are not checkpointed"):
        ckpt = save_checkpoint(tmp_path, step=1, modules={}, optimizers={}, replay_buffers={"b": buffer})
    monkeypatch.undo()
    assert (ckpt / "buffer_b" / "prefetch.pkl").exists()
    other = TensorDictReplayBuffer(storage=LazyTensorStorage(50), batch_size=4, prefetch=2)
    load_checkpoint(tmp_path, modules={}, optimizers={}, replay_buffers={"b": other})
    assert torch.equal(other[:]["x"], buffer[:]["x"])


def test_a_malicious_prefetch_pickle_is_refused(tmp_path):
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=2)
    buffer.extend(TensorDict({"x": torch.zeros(5, 1)}, batch_size=[5]))
    ckpt = save_checkpoint(tmp_path, step=1, modules={}, optimizers={}, replay_buffers={"b": buffer})
    path = ckpt / "buffer_b" / "prefetch.pkl"
    path.write_bytes(pickle.dumps({"version": 1, "capacity": 0, "queue": (Evil(tmp_path / "pwned"),)}))
    marker = json.loads((ckpt / "COMPLETE").read_text())
    marker["files"]["buffer_b/prefetch.pkl"] = {"bytes": path.stat().st_size,
                                                "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}
    (ckpt / "COMPLETE").write_text(json.dumps(marker))
    with pytest.raises(CheckpointError, match="refusing .*prefetch.pkl"):
        load_checkpoint(tmp_path, modules={}, optimizers={}, replay_buffers={"b": buffer})
    assert not (tmp_path / "pwned").exists()


def test_the_network_guard_blocks_remote_hosts(no_network):
    with pytest.raises(AssertionError, match="network access at run time"):
        socket.create_connection(("192.0.2.1", 80), timeout=0.1)  # TEST-NET-1: never routable
    no_network.clear()  # the attempt was the point of this test


def test_wandb_defaults_to_offline(monkeypatch):
    """wandb is off unless logger.backends names it, and its mode is wandb's own $WANDB_MODE, offline when unset."""
    from pe_rlhf.algorithms.proxy_q.config_schema import defaults
    from pe_rlhf.runtime.metrics_logger import wandb_mode

    assert defaults()["logger"]["backends"] == ["csv"]
    monkeypatch.delenv("WANDB_MODE", raising=False)
    assert wandb_mode() == "offline"
    monkeypatch.setenv("WANDB_MODE", "")
    assert wandb_mode() == "offline"
    monkeypatch.setenv("WANDB_MODE", "online")  # a user's own choice
    assert wandb_mode() == "online"


def test_wandb_offline_run_stays_on_this_machine(tmp_path, monkeypatch, no_network):
    """A run with ``logger.backends=[csv,wandb]`` and no ``$WANDB_MODE`` writes its files locally under the
    network guard (wandb's own service process talks to this one over loopback only)."""
    pytest.importorskip("wandb")
    from pe_rlhf.runtime.metrics_logger import MetricsLogger

    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.delenv("WANDB_MODE", raising=False)
    with MetricsLogger(tmp_path, backends=["csv", "wandb"], config={"lr": 1e-4}) as logger:
        logger.log(1, {"train/takeover_rate": 0.5})
        assert logger.wandb_run.offline
    assert list((tmp_path / "wandb").glob("offline-run-*/run-*.wandb"))


TELEMETRY_PROBE = """
import socket, sys, tempfile
from pathlib import Path
attempts, lookup = [], socket.getaddrinfo
def guarded(host, *args, **kwargs):
    if host not in ("localhost", "127.0.0.1", "::1", None, ""):
        attempts.append(host)
        raise OSError(f"blocked {host}")
    return lookup(host, *args, **kwargs)
socket.getaddrinfo = guarded
from pe_rlhf.runtime.metrics_logger import MetricsLogger
with MetricsLogger(Path(tempfile.mkdtemp()), backends=["csv", "wandb"], config={"lr": 1e-4}) as logger:
    logger.log(1, {"train/takeover_rate": 0.5})
from wandb.analytics.opentelemetry import opentelemetry_proxy
proxy = opentelemetry_proxy.get_open_telemetry_proxy()
if proxy is not None:
    proxy.shutdown()  # exports whatever telemetry the process recorded, now rather than on a timer
print("ATTEMPTS", attempts)
"""


def test_wandb_offline_run_sends_no_telemetry(tmp_path):
    """wandb records telemetry whatever the run's mode and a background thread posts it to its server (once seen
    as a network access in this suite): an offline run turns it off. In a fresh process, so that no earlier wandb
    use in this one decides; the telemetry is flushed at once instead of on wandb's timer."""
    pytest.importorskip("wandb")
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("WANDB_ERROR_REPORTING", "WANDB_MODE")}
    env["WANDB_SILENT"] = "true"
    done = subprocess.run([sys.executable, "-c", TELEMETRY_PROBE], env=env, capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "ATTEMPTS []" in done.stdout, done.stdout[-2000:]
