"""``benchmarks/shield.py``: importable, its agent hook checks the run folder, seeds of one method average, and a run
cut short goes on where it stopped."""

from __future__ import annotations

import json

import pytest
from _scripts import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("benchmarks/shield.py")


def test_agents_named_by_seed_get_a_mean_row(bench):
    row = lambda s, v, o: {"alone": {"success": s, "violation": v},  # noqa: E731
                           "shielded": {"success": s, "violation": 0.0, "override_share": o}}
    results = {"pe-rlhf-s0": row(0.6, 0.4, 0.1), "pe-rlhf-s1": row(0.8, 0.2, 0.3), "random": row(0, 1, 0.5)}
    means = bench.agent_means(results)
    assert list(means) == ["pe-rlhf-mean"]
    assert means["pe-rlhf-mean"]["alone"] == pytest.approx({"success": 0.7, "violation": 0.3})
    assert means["pe-rlhf-mean"]["shielded"]["override_share"] == pytest.approx(0.2)
    assert means["pe-rlhf-mean"]["seeds"] == ["pe-rlhf-s0", "pe-rlhf-s1"]


def test_an_agent_needs_an_existing_run_folder(bench, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench.main(["--agent", f"x={tmp_path / 'missing'}", "--policies"])
    assert "NAME=RUN_DIR with an existing run folder" in capsys.readouterr().err


@pytest.mark.slow
def test_shielded_never_brake_on_one_train_scene(bench, tmp_path):
    out = tmp_path / "s.json"
    results = bench.main(["--scenes", "2", "--policies", "never-brake", "--json", str(out)])
    assert results["never-brake"]["alone"]["violation"] == 1.0  # it crashes on scene 2 alone
    assert results["never-brake"]["shielded"]["violation"] == 0.0
    assert 0 < results["never-brake"]["shielded"]["override_share"] < 1
    assert results["decisions_per_second"] > 0 and out.exists()
    assert set(results["idm-mobil"]) == {"alone"}


def test_resume_keeps_the_policies_measured_on_the_same_scenes(bench, tmp_path):
    """A saved row of the same scenes is kept as it is (nothing is evaluated: the scene-0 row's marker values come
    back); its decisions count towards decisions_per_second. --resume without --json is a usage error."""
    face = {"success": 0.123, "violation": 0.0, "scene_seeds": [0]}
    saved = {"random": {"alone": face, "shielded": {**face, "override_share": 0.5, "decisions": 100,
                                                     "decision_latency_ms": 20.0}}}
    out = tmp_path / "s.json"
    out.write_text(json.dumps(saved))
    results = bench.main(["--scenes", "0", "--policies", "random", "--no-floor", "--json", str(out), "--resume"])
    assert results["random"] == saved["random"]
    assert results["decisions_per_second"] == pytest.approx(50.0)
    assert json.loads(out.read_text())["random"] == saved["random"]
    with pytest.raises(SystemExit):
        bench.main(["--scenes", "0", "--policies", "random", "--resume"])


def _evaluation(outcomes, shielded: bool) -> dict:
    """An evaluation summary's ``episodes_detail`` on scenes 0, 1, ...: ``outcomes`` "success" / "crash" / "timeout"."""
    detail = [{"scene_seed": i, "success": o == "success", "crash_vehicle": o == "crash", "crash_object": False,
               "out_of_road": False, "timeout": o == "timeout", "steps": 10,
               "decision_latency": 0.01 if shielded else None} for i, o in enumerate(outcomes)]
    return {"episodes_detail": detail, **({"override_share": 0.25} if shielded else {})}


def test_a_shielded_sweeps_trained_cells_join_as_agents_with_a_mean_and_the_rest_is_kept(bench, tmp_path, capsys):
    """``--from-sweep``: each trained cell with both evaluations is a ``<method>-<mentor>-s<seed>`` row read from its
    files (nothing is evaluated), the seeds get a mean row; a cell without its shielded evaluation, or evaluated on
    other scenes, is left out and said; the saved policies of the same scenes stay."""
    sweep = tmp_path / "sweep"
    cells = {"pe-rlhf__professional__s0": (["success", "crash"], ["success", "timeout"]),
             "pe-rlhf__professional__s1": (["success", "success"], ["success", "success"]),
             "pe-rlhf__professional__s2": (["crash", "crash"], None),
             "pvp__professional__s0": (["success"], ["success"]),
             "idm-mobil__s0": (["success", "timeout"], None)}
    for name, (alone, shielded) in cells.items():
        (sweep / name).mkdir(parents=True)
        method, *rest = name.split("__")
        info = {"method": method, "mentor": rest[0] if len(rest) == 2 else "-", "seed": int(name[-1]),
                "recipe": "evaluate" if method == "idm-mobil" else "pe_rlhf"}
        (sweep / name / "cell.json").write_text(json.dumps(info))
        (sweep / name / "final_eval.json").write_text(json.dumps(_evaluation(alone, False)))
        if shielded:
            (sweep / name / "shielded_eval.json").write_text(json.dumps(_evaluation(shielded, True)))
    face = {"success": 0.5, "violation": 0.0, "scene_seeds": [0, 1]}
    out = tmp_path / "summary.json"
    out.write_text(json.dumps({"random": {"alone": face, "shielded": {**face, "override_share": 0.1}}}))
    results = bench.main(["--scenes", "0-1", "--policies", "--no-floor", "--resume", "--json", str(out),
                          "--from-sweep", str(sweep)])
    printed = capsys.readouterr().out
    assert "left out pe-rlhf__professional__s2: no shielded_eval.json" in printed
    assert "left out pvp__professional__s0: evaluated on other scenes" in printed and "idm-mobil" not in printed
    agents = sorted(k for k in results if k.startswith("pe-rlhf"))
    assert agents == ["pe-rlhf-professional-mean", "pe-rlhf-professional-s0", "pe-rlhf-professional-s1"]
    s0 = results["pe-rlhf-professional-s0"]
    assert (s0["alone"]["success"], s0["alone"]["violation"]) == (0.5, 0.5)
    assert (s0["shielded"]["success"], s0["shielded"]["violation"], s0["shielded"]["override_share"]) == (0.5, 0, 0.25)
    mean = results["pe-rlhf-professional-mean"]
    assert mean["alone"]["success"] == pytest.approx(0.75) and mean["shielded"]["violation"] == 0.0
    assert "random" in results and "pvp-professional-s0" not in results and "idm-mobil-s0" not in results
    saved = json.loads(out.read_text())
    assert saved["pe-rlhf-professional-s1"]["shielded"]["success"] == 1.0 and "random" in saved
    assert saved["decisions_per_second"] == pytest.approx(100.0)  # 10 ms a decision in the cells' evaluations
