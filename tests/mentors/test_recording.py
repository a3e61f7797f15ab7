"""Tests for crash-safe demonstration recording (real env, real rule-based driver; no mocks)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.data import TensorDictReplayBuffer

from pe_rlhf.apps import cli
from pe_rlhf.envs import DrivingConfig, make_gym_env, scene_seeds
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.driver import PrivilegedDriver
from pe_rlhf.mentors.recording import (
    DemonstrationRecorder,
    dataset_info,
    load_demonstrations,
    read_manifest,
    record,
)
from _scripts import SCRIPT_ENV

SHORT = DrivingConfig(horizon=40)  # short episodes (time limit) keep the multi-episode tests fast


class DriverMentor(Mentor):
    """The privileged rule-based driver behind the Mentor interface."""

    name = "driver"

    def __init__(self):
        self.driver = PrivilegedDriver()

    def reset(self, env) -> None:
        self.driver.reset()

    def act(self, env) -> np.ndarray:
        return self.driver(env)

    def decide(self, env, agent_action) -> MentorDecision:
        return MentorDecision(False, self.act(env))


def _cli_mentor() -> str | None:
    """A registered simulated mentor's name, or None while the mentor registry does not exist."""
    try:
        import pe_rlhf.mentors.registry  # noqa: F401
    except ImportError:
        return None
    return "professional"


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> Path:
    """Two short episodes recorded with the default config."""
    d = tmp_path_factory.mktemp("demo") / "small"
    with DemonstrationRecorder(d, DrivingConfig(), "driver", seeds=[3, 4]) as rec:
        record(DriverMentor(), rec, 30, exact=True, progress=False)
        record(DriverMentor(), rec, 20, exact=True, progress=False)
    return d


def test_round_trip_matches_the_env(tmp_path):
    with DemonstrationRecorder(tmp_path / "d", DrivingConfig(), "driver", split="train") as rec:
        stats = record(DriverMentor(), rec, 300, progress=False)
        assert rec.steps == stats["steps"] >= 300 and rec.episodes == stats["episodes"] >= 1
    buffer = load_demonstrations(tmp_path / "d", DrivingConfig())
    assert isinstance(buffer, TensorDictReplayBuffer) and len(buffer) == stats["steps"]
    data = buffer[:]
    assert data["observation"].shape == (len(buffer), 250) and data["observation"].dtype == torch.float32
    assert data["action"].shape == (len(buffer), 2) and data["action"].abs().max() <= 1.0
    assert data["next", "reward"].shape == (len(buffer), 1) and data["next", "done"].dtype == torch.bool
    assert not data["done"].any() and data["scene_seed"][0].item() == scene_seeds("train")[0]
    for ep in data["episode"].unique().tolist():
        e = data[data["episode"].squeeze(-1) == ep]
        torch.testing.assert_close(e["next", "observation"][:-1], e["observation"][1:], rtol=0, atol=0)
        assert e["next", "done"][-1].item() and not e["next", "done"][:-1].any()
        # Replaying the stored actions reproduces the stored rewards and observations.
        env = make_gym_env(DrivingConfig())
        obs, _ = env.reset(options={"scene_seed": int(e["scene_seed"][0])})
        np.testing.assert_array_equal(obs, e["observation"][0].numpy())
        rewards = [env.step(a.numpy())[1] for a in e["action"]]
        np.testing.assert_allclose(e["next", "reward"].squeeze(-1).numpy(), np.float32(rewards), rtol=1e-6)
        assert bool(e["next", "success"][-1]) == read_manifest(tmp_path / "d")[ep]["success"]
    assert buffer.sample(8)["next", "observation"].shape == (8, 250)


def test_exact_stop_cuts_the_last_episode_as_truncated(small_dataset):
    entries = read_manifest(small_dataset)
    assert [e["steps"] for e in entries] == [30, 20] and [e["scene_seed"] for e in entries] == [3, 4]
    data = load_demonstrations(small_dataset)[:]
    assert len(data) == 50 and data["episode"].squeeze(-1).tolist() == [0] * 30 + [1] * 20
    assert data["next", "truncated"][[29, 49]].all() and data["next", "done"].sum() == 2
    info = dataset_info(small_dataset)
    assert info["episodes"] == 2 and info["steps"] == 50 and info["mentor"] == "driver"


def test_recorded_steps_equal_a_torchrl_rollout_of_the_same_actions(tmp_path):
    from pe_rlhf.envs.torchrl_env import make_env

    with DemonstrationRecorder(tmp_path / "t", SHORT, "driver", seeds=[5]) as rec:
        record(DriverMentor(), rec, 25, exact=True, progress=False)
        recorded = load_demonstrations(tmp_path / "t")[:]
        env = make_env(SHORT)
        actions = iter(recorded["action"])
        rollout = env.rollout(25, policy=lambda td: td.set("action", next(actions)), auto_reset=False,
                              tensordict=env.reset(scene_seed=5))
        rec.write_episode(rollout)  # a TorchRL rollout is a valid episode as it is
    both = load_demonstrations(tmp_path / "t", SHORT)[:]
    assert both["episode"].squeeze(-1).tolist() == [0] * 25 + [1] * 25
    first, second = both[:25].exclude("episode", "index"), both[25:].exclude("episode", "index")
    second["next", "truncated"][-1] = second["next", "done"][-1] = True  # the rollout stopped at 25, unmarked
    assert (first == second).all()


KILL_SCRIPT = """
import numpy as np
from pe_rlhf.envs import DrivingConfig
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.driver import PrivilegedDriver
from pe_rlhf.mentors.recording import DemonstrationRecorder, record

class DriverMentor(Mentor):
    def __init__(self): self.driver = PrivilegedDriver()
    def reset(self, env): self.driver.reset()
    def act(self, env): return self.driver(env)
    def decide(self, env, a): return MentorDecision(False, self.act(env))

rec = DemonstrationRecorder({out!r}, DrivingConfig(horizon=40), "driver", split="train")
record(DriverMentor(), rec, 10**6, progress=False)
"""


def test_sigkill_loses_at_most_the_current_episode_and_reopen_continues(tmp_path):
    out = tmp_path / "killed"
    name = _cli_mentor()
    if name:  # the real command line, with a registered simulated mentor
        cmd = [sys.executable, "-m", "pe_rlhf.apps.cli", "demo", "record", "--mentor", name, "--split", "train",
               "--steps", "1000000", "--out", str(out), "--config-override", "horizon=40", "--no-progress"]
    else:
        name, script = "driver", tmp_path / "rec.py"
        script.write_text(textwrap.dedent(KILL_SCRIPT.format(out=str(out))))
        cmd = [sys.executable, str(script)]
    env = {**os.environ, "PYTHONPATH": SCRIPT_ENV["PYTHONPATH"], "SDL_VIDEODRIVER": "dummy"}
    log = tmp_path / "stderr.txt"
    with open(log, "wb") as err:
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err)
    manifest = out / "manifest.jsonl"
    deadline = time.monotonic() + 60
    try:
        while not (manifest.exists() and manifest.read_text().count("\n") >= 2):
            assert proc.poll() is None, log.read_text()[-2000:]
            assert time.monotonic() < deadline, "recorder wrote no 2 episodes in 60 s"
            time.sleep(0.02)
        time.sleep(0.05)  # land somewhere inside a later episode
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    entries = read_manifest(out)
    n, seeds = len(entries), scene_seeds("train")
    assert n >= 2
    data = load_demonstrations(out, SHORT)[:]
    assert len(data) == sum(e["steps"] for e in entries)
    assert data["episode"].unique().tolist() == list(range(n))
    assert data["next", "done"].sum() == n  # every stored episode is complete
    # What a kill mid-write leaves behind: ignored by loading, deleted on reopen.
    (out / "episodes" / f".{n:06d}.pt.tmp").write_bytes(b"partial")
    (out / "episodes" / f"{n:06d}.pt").write_bytes(b"renamed, but not yet in the manifest")
    assert len(load_demonstrations(out)) == len(data)
    with DemonstrationRecorder(out, SHORT, name, split="train") as rec:
        assert sorted(p.name for p in (out / "episodes").iterdir()) == [Path(e["file"]).name for e in entries]
        assert rec.episodes == n and rec.next_scene_seed() == seeds[n % len(seeds)]
        record(DriverMentor(), rec, 60, progress=False)
        assert rec.episodes >= n + 2
    grown = load_demonstrations(out, SHORT)[:]
    assert len(grown) > len(data) and grown["episode"].unique().tolist() == list(range(rec.episodes))
    assert grown["scene_seed"][len(data)].item() == seeds[n % len(seeds)]
    assert dataset_info(out)["episodes"] == rec.episodes


def test_mismatched_config_or_mentor_is_refused(small_dataset):
    dense = DrivingConfig(traffic_density=0.9)
    with pytest.raises(ValueError, match=r"traffic_density: recorded 0\.5, requested 0\.9"):
        DemonstrationRecorder(small_dataset, dense, "driver", seeds=[3, 4])
    with pytest.raises(ValueError, match=r"traffic_density: recorded 0\.5, requested 0\.9"):
        load_demonstrations(small_dataset, dense)
    both = r"lanes: recorded 3, requested 4; mentor: recorded 'driver', requested 'amateur'"
    with pytest.raises(ValueError, match=both):
        DemonstrationRecorder(small_dataset, DrivingConfig(lanes=4), "amateur", seeds=[3, 4])
    with pytest.raises(ValueError, match=r"seeds: recorded \[3, 4\]"):
        DemonstrationRecorder(small_dataset, DrivingConfig(), "driver", seeds=[7])
    DemonstrationRecorder(small_dataset, dense, "driver", seeds=[3, 4], allow_mismatch=True).close()
    with DemonstrationRecorder(small_dataset, DrivingConfig(), "driver", seeds=[3, 4]):  # lock released
        with pytest.raises(RuntimeError, match="another process"):
            DemonstrationRecorder(small_dataset, DrivingConfig(), "driver", seeds=[3, 4])


def _rewrite_manifest_entry(d: Path, index: int, data: bytes) -> None:
    lines = (d / "manifest.jsonl").read_text().splitlines()
    entry = json.loads(lines[index])
    entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    lines[index] = json.dumps(entry)
    (d / "manifest.jsonl").write_text("\n".join(lines) + "\n")


def test_corruption_is_reported_with_the_file_name(small_dataset, tmp_path):
    d = tmp_path / "c"
    shutil.copytree(small_dataset, d)
    chunk = d / "episodes" / "000001.pt"
    chunk.write_bytes(chunk.read_bytes()[:1000])  # truncated
    with pytest.raises(ValueError, match=r"corrupt episode chunk .*000001\.pt"):
        load_demonstrations(d)
    _rewrite_manifest_entry(d, 1, b"garbage that is not a torch file")  # consistent checksum, bad content
    chunk.write_bytes(b"garbage that is not a torch file")
    with pytest.raises(ValueError, match=r"unreadable episode chunk .*000001\.pt"):
        load_demonstrations(d)
    chunk.unlink()
    with pytest.raises(ValueError, match=r"missing episode chunk .*000001\.pt"):
        load_demonstrations(d)
    with open(d / "manifest.jsonl", "a") as f:
        f.write("{garbage\n")
    with pytest.raises(ValueError, match=r"corrupt manifest .*manifest\.jsonl line 3"):
        load_demonstrations(d)
    with pytest.raises(ValueError, match=r"corrupt manifest .*manifest\.jsonl line 3"):
        DemonstrationRecorder(d, DrivingConfig(), "driver", seeds=[3, 4])


def test_cli_record_and_info(tmp_path, monkeypatch, capsys):
    mentor = _cli_mentor()
    if mentor is None:  # registry not written yet: the CLI still drives a real mentor
        mentor = "driver"
        monkeypatch.setattr(cli, "_make_mentor", lambda name, seed: DriverMentor())
    out = str(tmp_path / "cli")
    args = ["demo", "record", "--mentor", mentor, "--split", "train", "--steps", "50", "--out", out,
            "--seed", "0", "--config-override", "horizon=30", "--no-progress"]
    assert cli.main(args) == 0
    assert cli.main(args) == 0  # continues the dataset
    capsys.readouterr()
    assert cli.main(["demo", "info", out]) == 0
    text = capsys.readouterr().out
    info = dataset_info(out)
    assert info["episodes"] >= 4 and info["steps"] >= 100
    assert f"{info['episodes']} episodes" in text and f"{info['steps']} steps" in text and mentor in text
    with pytest.raises(SystemExit):  # continuing with another config is refused
        cli.main(args[:-3] + ["--no-progress"])
    assert "horizon: recorded 30, requested 1000" in capsys.readouterr().err


def test_cli_unknown_mentor_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["demo", "record", "--mentor", "nobody", "--steps", "5", "--out", str(tmp_path / "x")])
    assert "--mentor 'nobody'" in capsys.readouterr().err
