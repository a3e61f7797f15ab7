"""``benchmarks/evidence_grid.py``: the grid's cost from the named sweep configs, and each experiment's tables
(paired against its reference row, the claims' summary.json) from hand-made cells, without training."""

from __future__ import annotations

import csv
import json

import pytest
from _scripts import ROOT, load_script

from pe_rlhf.apps.sweeps import expand, load_sweep
from pe_rlhf.apps.sweeps.metrics import METRICS

HEADER = ["cell", "method", "mentor", "parameter", "seed", "status", *METRICS]


def _bench():
    return load_script("benchmarks/evidence_grid.py")


def _cells(path, rows):
    path.mkdir(parents=True)
    with open(path / "cells.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, HEADER)
        writer.writeheader()
        for method, mentor, parameter, seed, success in rows:
            writer.writerow({**{k: "nan" for k in HEADER}, "cell": f"{method}__{mentor}__{parameter}__s{seed}",
                             "method": method, "mentor": mentor, "parameter": parameter, "seed": seed,
                             "status": "finished", "success_rate": success, "safety_violation": 1 - success,
                             "train_safety_violations": seed, "takeover_data_usage": 0.3})


def test_the_dry_run_costs_every_training_cell_of_every_sweep(tmp_path, monkeypatch, capsys):
    bench = _bench()
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(bench, "EXPERT", tmp_path / "no_expert")
    monkeypatch.setattr(bench, "KEPT_EXPERT", tmp_path / "no_kept_expert")
    assert bench.main(["--dry-run", "--runs", str(tmp_path / "runs"), "--minutes-per-cell", "60"]) == 0
    printed = capsys.readouterr().out
    sweeps = [s for e in bench.EXPERIMENTS for s in e.sweeps]
    trained = sum(c.method.recipe != "evaluate" for s in sweeps for c in expand(load_sweep(bench.sweep_config(s))))
    assert f"to go: {trained + 1:.1f} core-hours at 60 min a training cell" in printed  # + the warm-up's expert
    assert all(f" {s} " in printed for s in sweeps)
    assert not (tmp_path / "runs").exists()


def test_summaries_pair_against_the_reference_row_and_the_claims_hold_each_mentor(tmp_path, monkeypatch, capsys):
    bench = _bench()
    monkeypatch.chdir(ROOT)
    runs, out = tmp_path / "runs", tmp_path / "out"
    _cells(runs / "physics_ablation", [("pe-rlhf", "professional", "idm+mobil", 0, 0.4),
                                       ("pe-rlhf", "professional", "idm+mobil", 1, 0.6),
                                       ("pe-rlhf", "professional", "mobil_only", 0, 0.7),
                                       ("pe-rlhf", "professional", "mobil_only", 1, 0.8)])
    _cells(runs / "mentor_proficiency", [(m, mentor, "-", s, 0.5) for m in ("pe-rlhf", "haco")
                                         for mentor in ("professional", "amateur") for s in (0, 1)])
    assert bench.main(["--summarise-only", "--only", "physics_ablation", "--only", "claims", "--only", "warmup",
                       "--runs", str(runs), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "warmup: no cells yet" in printed
    paired = (out / "physics_ablation" / "summary.md").read_text()
    assert "Paired by seed against `idm+mobil`" in paired
    assert "| pe-rlhf | professional | mobil_only | 2 | 0.25 [0.20, 0.30] |" in paired
    claims = json.loads((out / "claims" / "summary.json").read_text())
    assert sorted(claims) == ["amateur", "professional"] and claims["amateur"]["haco"]["seeds"] == 2
    assert claims["professional"]["pe_rlhf"]["success"] == pytest.approx([0.5, 0.5, 0.5])


def test_the_kept_expert_is_copied_in_rather_than_trained_again(tmp_path, monkeypatch):
    bench = _bench()
    kept, target = tmp_path / "kept", tmp_path / "runs" / "experts" / "sac_rs_seed0"
    kept.mkdir()
    (kept / "actor.pt").write_bytes(b"weights")
    (kept / "final_eval.json").write_text("{}")
    monkeypatch.setattr(bench, "EXPERT", target)
    monkeypatch.setattr(bench, "KEPT_EXPERT", kept)
    monkeypatch.setattr(bench.subprocess, "run", lambda *a, **k: pytest.fail("trained instead of copied"))
    bench.ensure_expert()
    assert (target / "actor.pt").read_bytes() == b"weights"
    bench.ensure_expert()  # there now: nothing to do


def test_it_must_run_from_the_repository_root(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit):
        _bench().main(["--dry-run"])
    assert "run from the repository root" in capsys.readouterr().err
