"""Claims over seeds: bootstrap intervals and the summary layout read from a sweep's cells.csv."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from pe_rlhf.apps.sweeps.claims import bootstrap_interval, claims_summary, markdown_table, write_claims

FIELDS = ["cell", "method", "mentor", "parameter", "seed", "status", "success_rate", "safety_violation",
          "train_safety_violations", "takeover_data_usage"]


def write_cells(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow(r)


def row(method, mentor, seed, success, violation, train=None, usage=None, status="finished"):
    return {"cell": f"{method}__{mentor}__s{seed}", "method": method, "mentor": mentor, "parameter": "-",
            "seed": seed, "status": status, "success_rate": success, "safety_violation": violation,
            "train_safety_violations": "nan" if train is None else train,
            "takeover_data_usage": "nan" if usage is None else usage}


def test_the_interval_brackets_the_mean_and_narrows_with_agreement():
    wide = bootstrap_interval([0.1, 0.5, 0.9, 0.3, 0.7])
    narrow = bootstrap_interval([0.49, 0.5, 0.51, 0.5, 0.5])
    assert wide[1] < wide[0] < wide[2] and narrow[1] <= narrow[0] <= narrow[2]
    assert narrow[2] - narrow[1] < wide[2] - wide[1]
    assert wide[0] == pytest.approx(0.5)
    assert bootstrap_interval([0.3]) == [0.3, 0.3, 0.3] == bootstrap_interval([0.3, 0.3, 0.3])
    assert bootstrap_interval([float("nan")]) is None
    assert bootstrap_interval([0.2, 0.4]) == bootstrap_interval([0.2, 0.4])  # seeded


def test_the_summary_groups_by_mentor_and_method(tmp_path):
    cells = tmp_path / "cells.csv"
    write_cells(cells, [row("pe-rlhf", "professional", s, v, 0.1, 3 + s, 0.3) for s, v in enumerate([0.6, 0.7, 0.8])]
                + [row("haco", "professional", 0, 0.5, 0.2, 4, 0.4),
                   row("haco", "professional", 1, 0.9, 0.0, 1, 0.2, status="running"),
                   row("idm-mobil", "-", 0, 0.42, 0.02), row("pe-rlhf", "adversarial", 0, 0.3, 0.2, 5, 0.3)])
    summary = write_claims(cells, tmp_path / "out")
    assert json.loads((tmp_path / "out" / "summary.json").read_text()) == summary
    pe = summary["professional"]["pe_rlhf"]
    assert pe["seeds"] == 3 and pe["success"][0] == pytest.approx(0.7) and pe["test_safety"][0] == pytest.approx(0.9)
    assert pe["success"][1] < 0.7 < pe["success"][2]
    assert summary["professional"]["haco"]["seeds"] == 1  # the running cell is not counted
    assert pe["per_seed"] == {"seed": [0, 1, 2], "success": [0.6, 0.7, 0.8],
                              "test_safety": pytest.approx([0.9, 0.9, 0.9])}
    idm = summary["professional"]["idm_mobil"]
    assert idm["train_violations"] is None and idm["success"] == pytest.approx([0.42] * 3)
    assert summary["adversarial"]["idm_mobil"] == idm and "-" not in summary  # beside every claim
    table = markdown_table(summary)
    assert "| professional | idm_mobil | 1 | 0.42 [0.42, 0.42] | 0.98 [0.98, 0.98] | — | — |" in table
    assert np.isfinite(pe["train_violations"]).all()
    assert claims_summary(cells) == summary


def test_each_method_can_come_from_its_own_sweep(tmp_path):
    old, new = tmp_path / "old.csv", tmp_path / "new.csv"
    write_cells(old, [row("pe-rlhf", "professional", 0, 0.2, 0.5, 9, 0.6),
                      row("haco", "professional", 0, 0.6, 0.1, 0, 0.2),
                      row("idm-mobil", "-", 0, 0.42, 0.02)])
    write_cells(new, [row("pe-rlhf", "professional", 0, 0.8, 0.0, 1, 0.3)])
    summary = claims_summary([f"{old}:haco,idm-mobil", f"{new}:pe-rlhf"])
    assert summary["professional"]["pe_rlhf"]["success"][0] == pytest.approx(0.8)  # the old pe-rlhf row is left out
    assert summary["professional"]["haco"]["success"][0] == pytest.approx(0.6)
    assert summary["professional"]["idm_mobil"]["seeds"] == 1
    assert claims_summary([old, new])["professional"]["pe_rlhf"]["seeds"] == 2  # no filter: both
    with pytest.raises(FileNotFoundError, match="no such cells.csv"):
        claims_summary([tmp_path / "missing.csv"])


def write_metrics(run_dir, totals):
    """A run folder whose metrics.csv logs ``totals`` (cumulative violations) every 100 env steps."""
    run_dir.mkdir(parents=True)
    with open(run_dir / "metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "env_steps", "train/safety_violations_total"])
        for i, total in enumerate(totals, start=1):
            w.writerow([i * 100, i * 100, total])


def test_violations_after_a_step_come_from_the_cumulative_count(tmp_path):
    from pe_rlhf.apps.sweeps.claims import violations_after

    write_metrics(tmp_path / "run", [0, 1, 1, 3, 7, 7])  # steps 100..600
    assert violations_after(tmp_path / "run", 300) == 6  # 7 at the end less 1 at step 300
    assert violations_after(tmp_path / "run", 350) == 6  # the last row at or before step 350 is step 300
    assert violations_after(tmp_path / "run", 50) == 7  # no row that early: all of them
    assert violations_after(tmp_path / "run", 600) == 0
    assert math.isnan(violations_after(tmp_path / "missing", 300))


def test_the_column_joins_the_summary_where_the_cells_carry_it(tmp_path):
    from pe_rlhf.apps.sweeps.claims import add_violations_after

    sweep = tmp_path / "sweep"
    sweep.mkdir()
    write_cells(sweep / "cells.csv", [row("pe-rlhf", "collapsing", 0, 0.5, 0.1, 9, 0.3),
                                      row("pe-rlhf", "collapsing", 1, 0.7, 0.1, 9, 0.3),
                                      row("idm-mobil", "-", 0, 0.42, 0.02)])
    write_metrics(sweep / "pe-rlhf__collapsing__s0", [1, 2, 5])
    write_metrics(sweep / "pe-rlhf__collapsing__s1", [0, 0, 2])
    rows = add_violations_after(sweep, 200, tmp_path / "cells_after.csv")
    assert [r["train_violations_after"] for r in rows[:2]] == [3, 2] and math.isnan(rows[2]["train_violations_after"])
    summary = claims_summary(tmp_path / "cells_after.csv")["collapsing"]
    assert summary["pe_rlhf"]["train_violations_after"][0] == pytest.approx(2.5)
    assert summary["idm_mobil"]["train_violations_after"] is None
    assert "train_violations_after" not in claims_summary(sweep / "cells.csv")["collapsing"]["pe_rlhf"]
    # a claim whose cells leave the column empty (a merged cells.csv) gets no such key
    with open(tmp_path / "cells_after.csv", "a", newline="") as f:
        csv.writer(f).writerow(["pe-rlhf__professional__s0", "pe-rlhf", "professional", "-", 0, "finished", 0.6, 0.1,
                                3, 0.3, ""])
    assert "train_violations_after" not in claims_summary(tmp_path / "cells_after.csv")["professional"]["pe_rlhf"]


def test_shielded_columns_join_the_claim_with_per_seed_lists_and_a_row_under_the_method(tmp_path):
    """Cells evaluated under the runtime shield too (a sweep with ``shield``) give each method of their claim the
    shielded success and safety, the override share, per-seed lists, and a ``<method> shielded`` row; a method
    without them (IDM-MOBIL) has ``null`` and no such row."""
    fields = FIELDS + ["shielded_success_rate", "shielded_safety_violation", "override_share"]
    cells = [{**row("pe-rlhf", "professional", s, ok, bad, 2, 0.3), "shielded_success_rate": sok,
              "shielded_safety_violation": sbad, "override_share": share}
             for s, ok, bad, sok, sbad, share in [(1, 0.6, 0.3, 0.62, 0.0, 0.05), (0, 0.8, 0.1, 0.78, 0.02, 0.03)]]
    cells.append({**row("idm-mobil", "-", 0, 0.42, 0.02), "shielded_success_rate": "nan",
                  "shielded_safety_violation": "nan", "override_share": "nan"})
    with open(tmp_path / "cells.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fields)
        writer.writeheader()
        writer.writerows(cells)
    claim = claims_summary(tmp_path / "cells.csv")["professional"]
    agent = claim["pe_rlhf"]
    assert agent["shielded_success"][0] == pytest.approx(0.70)
    assert agent["shielded_test_safety"][0] == pytest.approx(0.99)
    assert agent["override_share"][0] == pytest.approx(0.04)
    assert agent["per_seed"] == {"seed": [0, 1], "success": [0.8, 0.6], "test_safety": [0.9, pytest.approx(0.7)],
                                 "shielded_success": [0.78, 0.62], "shielded_test_safety": [0.98, 1.0]}
    assert claim["idm_mobil"]["shielded_success"] is None and "shielded_success" not in claim["idm_mobil"]["per_seed"]
    lines = markdown_table({"professional": claim}).splitlines()
    shielded = [line for line in lines if "shielded" in line]
    assert len(shielded) == 1 and shielded[0].startswith("| professional | pe_rlhf shielded (override share 0.040")
    assert "| 0.70 [" in shielded[0] and shielded[0].endswith("| — | — |")
    # cells from before the shield (no such columns): no shielded keys at all
    write_cells(tmp_path / "plain.csv", [row("pe-rlhf", "professional", 0, 0.8, 0.1, 2, 0.3)])
    plain = claims_summary(tmp_path / "plain.csv")["professional"]["pe_rlhf"]
    assert "shielded_success" not in plain and set(plain["per_seed"]) == {"seed", "success", "test_safety"}
