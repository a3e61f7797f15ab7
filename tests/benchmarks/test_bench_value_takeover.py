"""``benchmarks/value_takeover_curves.py`` on hand-made run folders: exact thirds, the figure, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _scripts import load_script


def _bench():
    return load_script("benchmarks/value_takeover_curves.py")


def _run(path: Path, chosen_per_batch: list[float], fatigue: bool) -> Path:
    """Warm-up of 2 batches of 100 steps, then batches with 50 takeover steps and the given mentor choices."""
    path.mkdir()
    (path / "config.yaml").write_text("collector:\n  warmup_steps: 200\n")
    lines = ["step,env_steps,train/takeover_rate,train/value_takeover_count,train/value_takeover_rate"
             + (",train/mentor_fatigue" if fatigue else "")]
    count = 0.0
    for i in range(2 + len(chosen_per_batch)):
        steps = 100 * (i + 1)
        online = i >= 2
        count += chosen_per_batch[i - 2] if online else 0.0
        rate = 0.5 if online else 1.0
        cumulative = count / max(50 * (i - 1), 1) if online else 0.0
        lines.append(f"{steps},{steps},{rate},{count},{cumulative}" + (f",{1 + 0.1 * i}" if fatigue else ""))
    (path / "metrics.csv").write_text("\n".join(lines) + "\n")
    return path


def test_thirds_figure_and_json(tmp_path):
    # 30 online batches: the mentor is chosen at 40 of 50 takeover steps, then 10 of 50 in the last 10
    falling = _run(tmp_path / "amateur", [40.0] * 20 + [10.0] * 10, fatigue=True)
    steady = _run(tmp_path / "pro", [45.0] * 30, fatigue=False)
    out, js = tmp_path / "fig.png", tmp_path / "vt.json"
    curves = _bench().main([f"amateur={falling}", f"pro={steady}", "--out", str(out), "--json", str(js)])
    assert out.stat().st_size > 0
    assert curves["pro"]["first_third"] == pytest.approx(0.9) and curves["pro"]["last_third"] == pytest.approx(0.9)
    assert curves["amateur"]["first_third"] == pytest.approx(0.8)
    # the last third (batches 21-30): batch 20 + k's window holds 10 - k high batches (40) and k low (10),
    # a rate of (400 - 30 k) / 500, whose mean over k = 1..10 is (400 - 165) / 500
    assert curves["amateur"]["last_third"] == pytest.approx(0.47)
    assert curves["amateur"]["last_third"] < curves["amateur"]["first_third"]
    saved = json.loads(js.read_text())
    assert saved["summary"]["pro"]["first_third"] == pytest.approx(0.9)
    assert saved["curves"]["amateur"]["fatigue"]["300.0"] == pytest.approx(1.2)


def test_bad_arguments_name_the_problem(tmp_path, capsys):
    with pytest.raises(SystemExit):
        _bench().main(["no-label", "--out", str(tmp_path / "f.png")])
    assert "LABEL=RUN_DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _bench().main([f"x={tmp_path}", "--out", str(tmp_path / "f.png")])
    assert "no metrics.csv" in capsys.readouterr().err
