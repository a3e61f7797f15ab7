"""Issue 45, case 9: a runtime failure a user can cause is one line and exit 2 (``--debug`` keeps the traceback);
a truncated newest checkpoint falls back to the intact one before it; a torn manifest line loses only its episode;
a malicious actor file is refused in one line naming it, without torch's advice to load it unsafely.
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import shutil
from pathlib import Path

import pytest
from _runs import train
from _scripts import ROOT, run_recipe, run_recipe_here

from pe_rlhf import durable
from pe_rlhf.runtime.checkpoint import CheckpointError

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


@pytest.fixture(scope="module")
def two_checkpoints(tmp_path_factory):
    out = tmp_path_factory.mktemp("failures") / "run"
    train(out, "collector.total_frames=200")
    return out


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def test_a_truncated_newest_checkpoint_falls_back_to_the_intact_one_before(two_checkpoints, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(two_checkpoints, out)
    truncate(out / "checkpoints" / "ckpt_000000200" / "tensors.pt")
    capsys.readouterr()
    final = train(out, "collector.total_frames=250", resume=True)
    said = capsys.readouterr().out
    assert "ckpt_000000200/tensors.pt is truncated or corrupt" in said
    assert "resuming from the intact ckpt_000000100" in said
    assert final["training"]["frames"] == 250


def test_a_runtime_failure_is_one_line_and_exit_2_and_debug_keeps_the_traceback(two_checkpoints, tmp_path,
                                                                               monkeypatch, capsys):
    out = tmp_path / "run"
    shutil.copytree(two_checkpoints, out)
    for step in (100, 200):
        truncate(out / "checkpoints" / f"ckpt_{step:09d}" / "tensors.pt")
    failed = run_recipe("pe_rlhf", "--resume", str(out), cwd=tmp_path)
    assert failed.returncode == 2
    lines = failed.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: CheckpointError: ") and "tensors.pt" in lines[0], lines
    assert "--debug shows the traceback" in lines[0]
    with pytest.raises(CheckpointError, match="tensors.pt"):  # raised, not turned into one line: Python prints it
        run_recipe_here("pe_rlhf", "--resume", str(out), "--debug", monkeypatch=monkeypatch, capsys=capsys)


def test_a_failed_atomic_write_reports_its_own_error_not_the_clean_up_s(tmp_path, monkeypatch):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(os, "replace", read_only)
    monkeypatch.setattr(Path, "unlink", read_only)  # the clean-up fails too, as on a read-only folder
    with pytest.raises(OSError) as info:
        durable.replace_bytes(tmp_path / "out.json", b"{}")
    assert info.value.errno == errno.EROFS and info.value.__context__ is None  # the write's error, not the unlink's


class Payload:
    def __reduce__(self):
        return (os.system, ("touch /tmp/pe_rlhf_pwned",))


def test_a_malicious_actor_in_a_baseline_run_is_refused_in_one_line(tmp_path):
    from pe_rlhf.algorithms.baselines import load_baseline_actor

    run = tmp_path / "expert"
    shutil.copytree(ROOT / "docs" / "results" / "claims" / "warmup" / "expert_sac_rs_seed0", run)
    (run / "actor.pt").write_bytes(pickle.dumps({"w": Payload()}))
    with pytest.raises(ValueError) as refused:
        load_baseline_actor(run)
    message = str(refused.value)
    assert message.startswith(f"refusing {run / 'actor.pt'}: ") and "\n" not in message
    assert "weights_only=False" not in message and len(message) < 400
    assert not Path("/tmp/pe_rlhf_pwned").exists()


def test_a_torn_manifest_line_loses_only_its_episode(tmp_path):
    from pe_rlhf.envs import DrivingConfig
    from pe_rlhf.mentors import make_mentor
    from pe_rlhf.mentors.recording import DemonstrationRecorder, load_demonstrations, read_manifest, record

    data = tmp_path / "demos"
    config = DrivingConfig(horizon=20)
    with DemonstrationRecorder(data, config, "professional", seeds=[3, 4, 5]) as rec:
        record(make_mentor("professional", seed=0), rec, 40, exact=True, progress=False)
    manifest = data / "manifest.jsonl"
    whole = read_manifest(data)
    assert len(whole) >= 2
    torn = manifest.read_bytes()[: -len(json.dumps(whole[-1])) // 2 - 1]  # the last line cut mid-write
    manifest.write_bytes(torn)
    with pytest.warns(UserWarning, match="line .* is torn .* that episode is lost"):
        kept = read_manifest(data)
    assert kept == whole[:-1]
    with pytest.warns(UserWarning, match="is torn"):
        steps = load_demonstrations(data)
    assert len(steps) == sum(e["steps"] for e in kept)
    with pytest.warns(UserWarning, match="is torn"), DemonstrationRecorder(data, config, "professional",
                                                                            seeds=[3, 4, 5]) as rec:  # reopened
        record(make_mentor("professional", seed=0), rec, 20, exact=True, progress=False)
    assert [e["episode"] for e in read_manifest(data)] == list(range(len(kept) + 1))
