"""``--resume`` from a checkpoint taken mid-episode and mid-takeover continues exactly as the run that went on.

A run trains to frame 150 with a checkpoint every 100 frames (60-step episodes: the one at 100 is 40 steps into
the second episode, inside a takeover). A copy of its folder reduced to the checkpoint at 100 (``latest`` there,
no journal: what a user keeps of a finished run) is resumed to 150: its checkpoint at 150 (buffers, counters,
networks, optimisers, RNG, the collection state) and its metrics rows must equal the original's, bit for bit.
The selector cases: the recipe's forecast rule (``builders.FORECAST_RULE``: a veto latches, physics keeps the
wheel until the mentor's action is no worse) at the shipped ``epsilon_select=-0.5`` and at ``0.5``, where the
mentor is vetoed more often; in both the checkpoint falls while physics drives under a held latch (the selector's
count, which must travel with the checkpoint: a resume that dropped it fails the shipped case, measured; at 0.5 a
fresh judgement vetoes the mentor all the same).

The checkpoint moved from frame 75 to 100 with the recipe's new defaults (the proxy-value loss's deterministic actor,
the takeover-balanced buffer, the latching forecast rule, the mentor's 5 m/s stall test): frame 75 now falls just
before a takeover, frame 100 inside one (measured, CPU).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from _compare import assert_same
from _runs import UNIFORM_REPLAY, checkpoint_contents, train

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]

MID, END = 100, 150
COMMON = ["env.horizon=60", f"checkpoint.every_frames={MID}", "checkpoint.keep=3"]
FORECAST = ["selector.value=forecast"]


def _ckpt(run: Path, step: int) -> Path:
    return run / "checkpoints" / f"ckpt_{step:09d}"


def _reduce_to_checkpoint(original: Path, copy: Path, step: int) -> Path:
    """A copy of ``original`` as it was at checkpoint ``step``: later checkpoints and the journal dropped."""
    shutil.copytree(original, copy)
    checkpoints = copy / "checkpoints"
    for path in checkpoints.glob("ckpt_*"):
        if int(path.name.removeprefix("ckpt_")) > step:
            shutil.rmtree(path)
    shutil.rmtree(checkpoints / "journal", ignore_errors=True)
    (checkpoints / "latest").write_text(f"ckpt_{step:09d}\n")
    return copy


def _metric_rows(run: Path) -> list[dict[str, str]]:
    """``metrics.csv`` without the wall-clock columns."""
    header, *rows = (run / "metrics.csv").read_text().splitlines()
    names = header.split(",")
    keep = [i for i, name in enumerate(names) if not (name.startswith("time/") or name == "wall_time")]
    return [{names[i]: row.split(",")[i] for i in keep} for row in rows]


@pytest.mark.parametrize("epsilon", [-0.5, 0.5], ids=["shipped", "vetoes"])
def test_resume_mid_takeover_matches_the_run_that_went_on(tmp_path, epsilon):
    original = tmp_path / "original"
    train(original, f"collector.total_frames={END}", *COMMON, *FORECAST, f"selector.epsilon_select={epsilon}")
    saved = json.loads((_ckpt(original, MID) / "state.json").read_text())["collection"]
    assert len(saved["env"]["actions"]) == MID - 60 and saved["takeover"]["in_takeover"]  # mid-episode, mid-takeover
    # physics drives (the selector's last choice was not the mentor) and the veto's latch holds: the selector state
    # the resumed run must continue
    assert saved["takeover"]["previous_choice"] is False and saved["takeover"]["selector"] == [1], saved["takeover"]

    resumed = _reduce_to_checkpoint(original, tmp_path / "resumed", MID)
    train(resumed, f"collector.total_frames={END}", resume=True)
    assert_same(checkpoint_contents(_ckpt(original, END)), checkpoint_contents(_ckpt(resumed, END)), "resumed")
    assert _metric_rows(resumed) == _metric_rows(original)


def test_a_checkpoint_without_collection_state_resumes_with_a_fresh_episode(tmp_path):
    """Checkpoints from before the collection state: ``--resume`` still loads them, and starts a new episode."""
    original = tmp_path / "original"
    train(original, f"collector.total_frames={MID}", *COMMON, UNIFORM_REPLAY)  # replay[frame] below: one buffer
    ckpt = _ckpt(original, MID)
    state = json.loads((ckpt / "state.json").read_text())
    del state["collection"]
    (ckpt / "state.json").write_text(json.dumps(state, indent=1, sort_keys=True))
    marker = json.loads((ckpt / "COMPLETE").read_text())  # the checksums follow the edited file
    data = (ckpt / "state.json").read_bytes()
    marker["files"]["state.json"] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    (ckpt / "COMPLETE").write_text(json.dumps(marker))

    final = train(original, f"collector.total_frames={MID + 25}", resume=True)
    assert final["training"]["frames"] == MID + 25
    replay = checkpoint_contents(_ckpt(original, MID + 25))["replay"]
    assert float(replay["travel_distance"][MID - 1]) > 0  # the checkpoint fell mid-episode...
    assert float(replay["travel_distance"][MID]) == 0  # ...and the resumed run went on from a new one's start
    assert int(replay["collector", "traj_ids"][MID]) == 0  # by a fresh collector
