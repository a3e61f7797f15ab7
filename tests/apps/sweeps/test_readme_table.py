"""README's results table: rendered from ``docs/results/claims/summary.json`` by ``readme_table``, and README holds
exactly that rendering between its markers, so the two cannot drift apart."""

from __future__ import annotations

import json

import pytest
from _scripts import ROOT, load_script

from pe_rlhf.apps.sweeps.claims import (README_TABLE_END, README_TABLE_START, readme_table, readme_table_in,
                                        with_readme_table)

SUMMARY = ROOT / "docs" / "results" / "claims" / "summary.json"


def entry(success, seeds=3, train=(1.0, 0.0, 2.0), usage=(0.25, 0.2, 0.3)):
    return {"success": list(success), "test_safety": [0.9, 0.8, 1.0], "train_violations": None if train is None
            else list(train), "takeover_usage": None if usage is None else list(usage), "seeds": seeds}


def rows(table: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()[2:] if line.startswith("|")]


def test_readme_shows_exactly_the_table_of_summary_json():
    table = readme_table(json.loads(SUMMARY.read_text()))
    readme = (ROOT / "README.md").read_text()
    assert readme_table_in(readme) == table
    assert f"{README_TABLE_START}\n{table}\n{README_TABLE_END}" in readme


def test_labels_order_and_cells():
    idm = entry((0.42, 0.42, 0.42), seeds=1, train=None, usage=None)
    summary = {"amateur": {"idm_mobil": idm, "zeta": entry((0.1, 0.0, 0.2)), "haco": entry((0.5, 0.4, 0.6))},
               "professional": {"pvp": entry((0.8, 0.7, 0.9), seeds=5), "pe_rlhf_paper_loss": entry((0.6, 0.5, 0.7)),
                                "idm_mobil": idm,
                                "pe_rlhf": {**entry((0.85, 0.75, 0.95), seeds=5),
                                            "per_seed": {"seed": [0], "success": [0.8], "test_safety": [0.9]}}}}
    got = rows(readme_table(summary))
    # the professional first, then the others as given; the paper's methods in reading order, unknown names last;
    # the evaluated-only IDM-MOBIL once, under the first mentor (it has no mentor)
    assert [(r[0], r[1]) for r in got] == [
        ("professional", "PE-RLHF"), ("professional", "PE-RLHF (paper's loss)"), ("professional", "PVP"),
        ("professional", "IDM-MOBIL"), ("amateur", "HACO"), ("amateur", "zeta")]
    assert got[0] == ["professional", "PE-RLHF", "5", "0.85 [0.75, 0.95]", "0.90 [0.80, 1.00]", "1.0 [0.0, 2.0]",
                      "0.25 [0.20, 0.30]"]
    # an evaluated-only method: one value where every seed agrees, a dash where it has no such metric
    assert got[3] == ["professional", "IDM-MOBIL", "—", "0.42", "0.90 [0.80, 1.00]", "—", "—"]
    assert "needs no mentor" in readme_table(summary).splitlines()[-1]


def test_the_line_under_the_table_says_steps_and_scenes():
    text = readme_table({"professional": {"pe_rlhf": entry((0.5, 0.4, 0.6))}}, steps=20_000, warmup=5_000,
                        scenes="test scenes 1000-1009")
    last = text.splitlines()[-1]
    assert "20K env steps" in last and "5K of them" in last and "test scenes 1000-1009" in last
    assert "over seeds" in last


def test_a_missing_or_nan_metric_is_a_dash():
    m = entry((0.5, 0.4, 0.6))
    m["test_safety"] = [float("nan"), float("nan"), float("nan")]
    del m["takeover_usage"]
    (row,) = rows(readme_table({"professional": {"pe_rlhf": m}}))
    assert row[4] == "—" and row[6] == "—"


def test_the_table_is_replaced_between_the_markers_only():
    text = f"# title\n\nbefore\n{README_TABLE_START}\nold | table\n{README_TABLE_END}\nafter\n"
    new = with_readme_table(text, "| new |")
    assert new == f"# title\n\nbefore\n{README_TABLE_START}\n| new |\n{README_TABLE_END}\nafter\n"
    assert with_readme_table(new, "| new |") == new  # idempotent
    assert readme_table_in(new) == "| new |"
    with pytest.raises(ValueError, match="claims-table"):
        with_readme_table("# no markers\n", "| new |")
    with pytest.raises(ValueError, match="once each"):
        with_readme_table(f"{README_TABLE_END}\n{README_TABLE_START}\n", "| new |")


def test_the_script_rewrites_a_readme_from_summary_json(tmp_path, capsys):
    bench = load_script("benchmarks/claims_summary.py")
    summary = {"professional": {"pe_rlhf": entry((0.5, 0.4, 0.6)), "idm_mobil": entry((0.42,) * 3, 1, None, None)}}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{README_TABLE_START}\nstale\n{README_TABLE_END}\nend\n")
    bench.main(["--readme", str(readme), "--out", str(tmp_path)])
    assert readme_table_in(readme.read_text()) == readme_table(summary)
    assert readme.read_text().startswith("intro\n") and readme.read_text().endswith("end\n")
    bad = tmp_path / "BAD.md"
    bad.write_text("no markers\n")
    with pytest.raises(SystemExit):
        bench.main(["--readme", str(bad), "--out", str(tmp_path)])
    assert "BAD.md" in capsys.readouterr().err


def test_a_shielded_method_gets_a_column_and_the_line_says_what_it_is():
    agent = {**entry((0.6, 0.5, 0.7), seeds=5), "shielded_success": [0.62, 0.55, 0.7],
             "shielded_test_safety": [1.0, 1.0, 1.0], "override_share": [0.05, 0.04, 0.06]}
    other = {**entry((0.3, 0.2, 0.4)), "shielded_success": [0.5, 0.4, 0.6], "shielded_test_safety": [0.98, 0.96, 1.0],
             "override_share": [0.1, 0.05, 0.2]}
    summary = {"professional": {"pe_rlhf": agent, "idm_mobil": {**entry((0.42, 0.42, 0.42), seeds=1, train=None,
                                                                        usage=None), "shielded_success": None}},
               "adversarial": {"haco": other}}
    text = readme_table(summary)
    assert text.splitlines()[0].split("|")[6].strip() == "shielded success"
    got = rows(text)
    assert [r[1] for r in got] == ["PE-RLHF", "IDM-MOBIL", "HACO"]
    assert got[0] == ["professional", "PE-RLHF", "5", "0.60 [0.50, 0.70]", "0.90 [0.80, 1.00]", "0.62 [0.55, 0.70]",
                      "1.0 [0.0, 2.0]", "0.25 [0.20, 0.30]"]
    assert got[1][5] == "—"  # IDM-MOBIL is not an agent under the shield
    last = text.splitlines()[-1]
    assert "runtime shield" in last and "0.98 or above in every row" in last  # the lowest shielded test safety
    plain = readme_table({"professional": {"pe_rlhf": entry((0.6, 0.5, 0.7))}})
    assert "shield" not in plain and len(rows(plain)[0]) == 7
