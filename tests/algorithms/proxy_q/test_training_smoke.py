"""The PE-RLHF recipe end to end on the smoke profile: every output written, metrics finite."""

from __future__ import annotations

import csv
import json
import math

import pytest
from _scripts import load_pe_rlhf_recipe

from pe_rlhf.durable import load_tensors

SMOKE_RUN = ["profile=smoke", "eval.video=true", "--compare", "idm-mobil", "--shield"]


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    """One smoke run (``SMOKE_RUN``): its folder and the summary the recipe returned."""
    out = tmp_path_factory.mktemp("smoke_run")
    return out, load_pe_rlhf_recipe().main([*SMOKE_RUN, "--out", str(out)])


def _logged(out, final) -> tuple:
    """Every logged number but the timings, and the final evaluation's rates."""
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    return ([{k: v for k, v in r.items() if not k.startswith("time/") and k != "wall_time"} for r in rows],
            final["success_rate"], final["episodic_return"])


def test_smoke_run_writes_every_output(smoke_run):
    tmp_path, final = smoke_run
    for name in ("config.yaml", "metrics.csv", "final_eval.json", "training_curves.png", "actor.safetensors",
                 "test_episode.gif"):
        assert (tmp_path / name).exists(), name
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert len(rows) == 300 // 50  # one row per collected batch
    steps = [int(float(r["step"])) for r in rows]
    assert steps == sorted(steps) and steps[-1] == 300
    for row in rows:
        for key, value in row.items():
            if value != "":
                assert math.isfinite(float(value)), key
    # warm-up (100 steps): the mentor drives every step; afterwards the takeover rate is a real rate
    assert float(rows[0]["train/takeover_rate"]) == 1.0
    assert 0.0 <= float(rows[-1]["train/takeover_data_usage"]) <= 1.0
    assert any(r.get("loss/qvalue") for r in rows[1:])  # updates ran
    saved = json.load(open(tmp_path / "final_eval.json"))
    assert saved["episodes"] == 1 and 0.0 <= saved["success_rate"]["mean"] <= 1.0
    assert final["training"]["frames"] == 300
    reference = json.load(open(tmp_path / "reference_idm-mobil.json"))  # --compare: same scenes, other policy
    assert reference["policy"] == "idm-mobil" and reference["seeds"] == saved["seeds"]
    shielded = json.load(open(tmp_path / "shielded_eval.json"))  # --shield: the trained actor under the shield
    assert shielded["seeds"] == saved["seeds"] and 0.0 <= shielded["override_share"] <= 1.0
    assert shielded["decision_latency_ms"]["mean"] > 0
    assert 1 <= final["video"]["steps"] <= 100 and final["video"]["path"].endswith("test_episode.gif")
    # the trained agent evaluates from its run folder, reproducing the recipe's final evaluation
    from pe_rlhf.apps.cli import main as cli

    assert cli(["evaluate", "--checkpoint", str(tmp_path), "--seeds", "1000", "--no-progress",
                "--config-override", "horizon=100", "--config-override", "min_blocks=2",
                "--config-override", "max_blocks=2", "--json", str(tmp_path / "again.json")]) == 0
    again = json.load(open(tmp_path / "again.json"))
    assert again["episodic_return"]["mean"] == saved["episodic_return"]["mean"]


@pytest.mark.parametrize("argv, threshold", [([], None), (["--shield"], 0.5), (["--shield", "1.5"], 1.5)])
def test_the_shield_flag_takes_an_optional_threshold(argv, threshold):
    from pe_rlhf.runtime.recipe import parse_command_line

    options, rest = parse_command_line([*argv, "profile=smoke"])
    assert options.shield == threshold and rest == ["profile=smoke"]


def test_a_bad_shield_threshold_fails_in_one_line(capsys):
    from pe_rlhf.runtime.recipe import parse_command_line

    with pytest.raises(SystemExit) as exit_info:
        parse_command_line(["--shield=-1", "profile=smoke"])
    assert exit_info.value.code == 2 and "a threshold in seconds >= 0" in capsys.readouterr().err


def test_unknown_compare_policy_fails_before_training(tmp_path, capsys):
    with pytest.raises(SystemExit):
        load_pe_rlhf_recipe().main(["profile=smoke", "--out", str(tmp_path), "--compare", "idm-mobl"])
    assert "allowed" in capsys.readouterr().err and not (tmp_path / "metrics.csv").exists()


def test_resume_continues_without_gap_or_repeat(tmp_path, capsys):
    recipe = load_pe_rlhf_recipe()
    recipe.main(["profile=smoke", "collector.total_frames=200", "checkpoint.every_frames=100", "checkpoint.keep=2",
                 "eval.video=false", "--out", str(tmp_path)])  # no GIF: test_smoke_run_writes_every_output's
    assert (tmp_path / "checkpoints" / "ckpt_000000200").exists()
    final = recipe.main(["--resume", str(tmp_path), "collector.total_frames=300"])
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    steps = [int(float(r["step"])) for r in rows]
    assert steps == [50, 100, 150, 200, 250, 300]  # the curve continues: no gap, no repeated step
    assert final["training"]["frames"] == 300
    # warm-up (100 frames) happened once: after resuming, the takeover bookkeeping counts online frames only
    assert final["training"]["online_frames"] == 200
    capsys.readouterr()
    again = recipe.main(["--resume", str(tmp_path), "collector.total_frames=300", "eval.video=false"])
    assert "the run was already complete (300 of 300 frames); evaluating it again" in capsys.readouterr().out
    assert again["training"]["frames"] == 300 and len(list(csv.DictReader(open(tmp_path / "metrics.csv")))) == 6


def test_amateur_fatigue_is_logged_and_grows_with_the_steps_it_controls(tmp_path):
    """``train/mentor_fatigue`` = ``min(1 + fatigue_rate * controlled_steps / 1000, cap)``: it never falls,
    and the steps the amateur held control in the run (at least every online takeover step) raised it."""
    load_pe_rlhf_recipe().main(["profile=smoke", "eval.video=false", "mentor.name=amateur",
                         "mentor.kwargs.fatigue_rate=2.0", "--out", str(tmp_path)])
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    fatigue = [float(r["train/mentor_fatigue"]) for r in rows]
    assert fatigue == sorted(fatigue) and 1.0 < fatigue[-1] <= 3.0
    online_takeover_steps = float(rows[-1]["train/takeover_data_usage"]) * (300 - 100)
    assert fatigue[-1] >= 1.0 + 2.0 * online_takeover_steps / 1000 - 1e-6


def test_the_same_seed_gives_the_same_metrics(smoke_run, tmp_path):
    """Two runs of one seed on one machine: every logged number and the final evaluation agree (timings aside).
    The second records no GIF (a third of its CPU): the video is filmed after the final evaluation."""
    again = load_pe_rlhf_recipe().main([*SMOKE_RUN, "eval.video=false", "--out", str(tmp_path)])
    assert _logged(tmp_path, again) == _logged(*smoke_run)


def test_actor_selection_in_the_recipe_keeps_the_picked_checkpoints_actor(tmp_path, capsys):
    """actor_selection.every_frames: the PE-RLHF run scores its actor on train scenes at each checkpoint's
    step, ``actor.pt`` is the picked one (the actor of that checkpoint), and the last one's test evaluation
    stays in final_eval.json and in the printed table."""
    import torch

    from pe_rlhf.algorithms.proxy_q.trained_policy import load_actor

    final = load_pe_rlhf_recipe().main(["profile=smoke", "eval.video=false", "actor_selection.every_frames=100",
                                        "actor_selection.episodes=1", "checkpoint.every_frames=100",
                                        "checkpoint.keep=3", "--out", str(tmp_path)])
    picking = final["actor_selection"]
    assert sorted(map(int, picking["scores"])) == [100, 200, 300] and picking["split"] == "train"
    assert picking["picked_step"] in (100, 200, 300)
    assert final["last_actor"]["episodes"] == final["episodes"] == 1
    saved = load_tensors(tmp_path / "actor.safetensors")[0]
    at_pick = load_actor(tmp_path, checkpoint=tmp_path / "checkpoints" / f"ckpt_{picking['picked_step']:09d}")
    for k, v in at_pick.state_dict().items():
        assert torch.equal(saved[k], v), k
    assert f"the actor of frame {picking['picked_step']}, picked on 1 train scenes" in capsys.readouterr().out
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert [r["actor_selection/success_rate"] != "" for r in rows] == [int(float(r["step"])) % 100 == 0 for r in rows]
