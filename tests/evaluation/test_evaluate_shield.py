"""``pe-rlhf evaluate --shield``: the policy drives under the runtime shield; the summary reports the share of
steps the shield overrode and the time of a decision."""

from __future__ import annotations

import json

import pytest

from pe_rlhf.apps.cli import main


def test_evaluate_shield_reports_override_share_and_latency(tmp_path, capsys):
    alone, shielded = tmp_path / "alone.json", tmp_path / "shielded.json"
    args = ["evaluate", "--policy", "never-brake", "--seeds", "5", "--no-progress"]
    assert main([*args, "--json", str(alone)]) == 0
    assert main([*args, "--shield", "--json", str(shielded)]) == 0
    a, s = json.loads(alone.read_text()), json.loads(shielded.read_text())
    assert "override_share" not in a
    assert a["safety_violation"]["mean"] > 0  # never braking, it crashes on this train scene
    assert s["safety_violation"]["mean"] == 0 and s["policy"] == "never-brake shielded"
    assert s["success_rate"]["mean"] == 1.0  # the shield brakes where the policy would not, and hands back
    assert 0 < s["override_share"] < 1
    assert 0 < s["decision_latency_ms"]["mean"] < 50  # >= 20 decisions a second
    detail = s["episodes_detail"][0]
    assert s["override_share"] == pytest.approx(detail["override_steps"] / detail["steps"])
    assert "override share" in capsys.readouterr().out


@pytest.mark.parametrize("value", ["-1", "soon", "inf"])
def test_evaluate_shield_rejects_a_bad_threshold(value, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--no-progress", "--shield", value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"--shield {value!r}" in err and "Traceback" not in err
