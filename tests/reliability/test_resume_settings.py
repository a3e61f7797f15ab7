"""Issue 45, case 5: a resume states what it changes: each changed setting is applied (optimiser settings included)
or refused in one line naming it; never ignored.

Before: ``--resume D optim.lr=0.001`` ran on at the saved 1e-4 (the optimiser state restored it) and ``config.yaml``
kept the old value; ``--resume D checkpoint.every_frames=0`` silently threw the journal away.
"""

from __future__ import annotations

import shutil

import pytest
import torch
import yaml
from _runs import train

from pe_rlhf.runtime.config_rules import ConfigError

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


@pytest.fixture(scope="module")
def checkpointed(tmp_path_factory):
    out = tmp_path_factory.mktemp("settings") / "run"
    train(out, "collector.total_frames=100")
    return out


def test_a_changed_learning_rate_is_applied_said_and_saved(checkpointed, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(checkpointed, out)
    capsys.readouterr()
    train(out, "collector.total_frames=150", "optim.lr=0.001", resume=True)
    said = capsys.readouterr().out
    assert "resume: optim.lr 0.0001 -> 0.001 (applied)" in said
    assert "resume: collector.total_frames 100 -> 150 (applied)" in said
    optimizers = torch.load(out / "checkpoints" / "ckpt_000000150" / "tensors.pt", weights_only=True)["optimizers"]
    assert {g["lr"] for opt in optimizers.values() for g in opt["param_groups"]} == {0.001}
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["optim"]["lr"] == 0.001 and saved["collector"]["total_frames"] == 150


@pytest.mark.parametrize(("override", "named"), [("seed=3", "seed"), ("checkpoint.every_frames=0", "checkpoint.every_frames"),
                                                  ("collector.frames_per_batch=50", "collector.frames_per_batch"),
                                                  ("mentor.name=amateur", "mentor.name")])
def test_a_setting_a_resume_cannot_apply_is_refused_in_one_line(checkpointed, override, named):
    before = (checkpointed / "config.yaml").read_text()
    with pytest.raises(ConfigError) as refused:
        train(checkpointed, "collector.total_frames=150", override, resume=True)
    message = str(refused.value)
    assert "\n" not in message and f"a resume cannot change {named} " in message and refused.value.field == named
    assert (checkpointed / "config.yaml").read_text() == before  # nothing written


def test_a_run_saved_before_issue_43_resumes_and_saves_the_new_settings(checkpointed, tmp_path, capsys):
    """A run folder whose config.yaml holds the retired logger switches, ``mentor.seed`` and
    ``actor_selection.split`` (at their defaults) resumes as if saved now, with nothing announced as changed."""
    out = tmp_path / "run"
    shutil.copytree(checkpointed, out)
    saved = yaml.safe_load((out / "config.yaml").read_text())
    logger = saved["logger"]
    saved["logger"] = {"out_dir": None, "csv": True, "wandb": False, "wandb_mode": "offline",
                       "wandb_project": logger["project"], "tensorboard": False, "mlflow": False,
                       "log_every": logger["log_every"]}
    saved["mentor"]["seed"] = saved["seed"]
    saved["actor_selection"]["split"] = "train"
    (out / "config.yaml").write_text(yaml.safe_dump(saved, sort_keys=False))
    capsys.readouterr()
    train(out, "collector.total_frames=150", resume=True)
    said = capsys.readouterr().out
    assert [line for line in said.splitlines() if line.startswith("resume:")] == [
        "resume: collector.total_frames 100 -> 150 (applied)"]
    now = yaml.safe_load((out / "config.yaml").read_text())
    assert now["logger"] == {"backends": ["csv"], "project": "pe-rlhf", "log_every": 1}
    assert "seed" not in now["mentor"] and "split" not in now["actor_selection"]
    assert (out / "checkpoints" / "ckpt_000000150").is_dir()
