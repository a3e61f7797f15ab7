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
