"""``optim.device``: the learner on a device, acting on a CPU copy synced after each round of updates.

No GPU here: the copy path runs with the learner on the CPU (``learner_device`` forced to ``cpu``), where it
must reproduce the shared-actor path bit for bit, and a CUDA-saved checkpoint is simulated by loading CPU
tensors into modules wherever they live (``map_location="cpu"`` then ``load_state_dict``)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from _scripts import load_script

from pe_rlhf.durable import load_tensors
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config

_runs = load_script("tests/reliability/_runs.py", "reliability_runs")
TIMING, train = _runs.TIMING, _runs.train

pytestmark = pytest.mark.usefixtures("one_thread_module")


def _rows(out: Path) -> list[dict]:
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    return [{k: v for k, v in r.items() if not k.startswith("time/") and k != "wall_time"
             and not any(t in k for t in TIMING)} for r in rows]


def test_learner_device_resolution():
    assert builders.learner_device(load_config(overrides=["optim.device=cpu"])) is None
    auto = builders.learner_device(load_config())
    assert auto is None if not torch.cuda.is_available() else auto.type == "cuda"
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="optim.device='cuda': torch sees no CUDA device"):
            builders.learner_device(load_config(overrides=["optim.device=cuda"]))
    with pytest.raises(ConfigError, match="optim.device='tpu' is invalid: allowed: auto, cpu, cuda, cuda:N"):
        load_config(overrides=["optim.device=tpu"])


def test_acting_on_a_synced_copy_reproduces_the_shared_actor_run(tmp_path, monkeypatch):
    """The copy path (learner's loss on ``device``, a CPU acting copy refreshed after every round) gives the
    same metrics as acting with the learner's own actor: in sync mode acting never overlaps an update."""
    shared = train(tmp_path / "shared", "collector.total_frames=150")
    monkeypatch.setattr(builders, "learner_device", lambda cfg: torch.device("cpu"))
    built = []
    real_build = builders.build_updater
    monkeypatch.setattr(builders, "build_updater", lambda *a, **k: built.append(real_build(*a, **k)) or built[-1])
    copied = train(tmp_path / "copied", "collector.total_frames=150")
    (updater,) = built
    assert updater.device == torch.device("cpu") and updater.policy is updater.acting_actor
    assert updater.acting_actor is not updater.actor  # a separate module...
    for a, b in zip(updater.actor.parameters(), updater.acting_actor.parameters()):
        assert a.data_ptr() != b.data_ptr() and torch.equal(a, b)  # ...holding the learner's last weights
    assert _rows(tmp_path / "copied") == _rows(tmp_path / "shared")
    assert copied["success_rate"] == shared["success_rate"]
    actor = load_tensors(tmp_path / "copied" / "actor.safetensors")[0]
    assert all(v.device.type == "cpu" for v in actor.values())


def test_a_checkpoint_resumes_whatever_device_saved_it(tmp_path):
    """Checkpoint tensors are read with ``map_location="cpu"`` and copied into the modules where they live,
    so a run saved on a GPU resumes on a CPU-only machine (and the other way): here the resumed run's
    modules receive the saved values through ``load_state_dict``, as they would from CUDA tensors."""
    from pe_rlhf.runtime.checkpoint import find_checkpoint

    train(tmp_path / "run", "collector.total_frames=100")
    ckpt = find_checkpoint(tmp_path / "run" / "checkpoints")
    tensors = torch.load(ckpt / "tensors.pt", weights_only=True, map_location="cpu")
    saved = tensors["modules"]["loss"]
    assert all(v.device.type == "cpu" for v in saved.values() if isinstance(v, torch.Tensor))
    final = train(tmp_path / "run", "collector.total_frames=150", resume=True)
    assert final["training"]["frames"] == 150


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_run_with_the_learner_on_cuda_trains_and_saves_a_cpu_actor(tmp_path):
    """On a GPU: the loss module and its updates on CUDA, acting and evaluation on the synced CPU copy. The run
    trains (finite losses in every row), saves its actor as CPU tensors (loadable with no GPU), and resumes."""
    built = []
    real_build = builders.build_updater
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(builders, "build_updater", lambda *a, **k: built.append(real_build(*a, **k)) or built[-1])
        train(tmp_path / "run", "collector.total_frames=100", "optim.device=cuda")
    (updater,) = built
    assert updater.device.type == "cuda"
    assert all(p.device.type == "cuda" for p in updater.actor.parameters())
    assert all(p.device.type == "cpu" for p in updater.acting_actor.parameters())
    for a, b in zip(updater.actor.parameters(), updater.acting_actor.parameters()):
        assert torch.equal(a.detach().cpu(), b)  # the acting copy holds the learner's last weights
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    losses = [float(v) for r in rows for k, v in r.items() if k.startswith("loss/") and v not in ("", None)]
    assert losses and all(torch.isfinite(torch.tensor(losses)))
    actor = load_tensors(tmp_path / "run" / "actor.safetensors")[0]
    assert all(v.device.type == "cpu" for v in actor.values())
    final = train(tmp_path / "run", "collector.total_frames=150", resume=True)
    assert final["training"]["frames"] == 150
