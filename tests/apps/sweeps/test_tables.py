"""A summary from cells.csv rows alone (pe_rlhf.apps.sweeps.tables): grouping, intervals, paired differences."""

from __future__ import annotations

import csv

import pytest

from pe_rlhf.apps.sweeps.metrics import METRICS
from pe_rlhf.apps.sweeps.tables import numeric_parameters, paired_differences, read_rows, summarise_cells

HEADER = ["cell", "method", "mentor", "parameter", "seed", "status", *METRICS]


def _write(path, rows):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, HEADER)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "nan") for k in HEADER})
    return path


def _row(parameter, seed, success, status="finished", method="pe-rlhf", mentor="professional"):
    return {"cell": f"{method}__{parameter}__s{seed}", "method": method, "mentor": mentor, "parameter": parameter,
            "seed": seed, "status": status, "success_rate": success, "train_safety_violations": seed}


def test_rows_from_two_files_group_by_parameter_with_intervals_and_paired_differences(tmp_path):
    a = _write(tmp_path / "a.csv", [_row("full", 0, 0.4), _row("full", 1, 0.6), _row("ablated", 0, 0.1)])
    b = _write(tmp_path / "b.csv", [_row("ablated", 1, 0.4), _row("ablated", 2, 0.9, status="unfinished"),
                                     _row("-", 0, 0.5, method="idm-mobil", mentor="-")])
    result = summarise_cells([a, b], tmp_path / "out", ["success_rate", "train_safety_violations"],
                             title="T", paired_against="full")
    table = {(r["method"], r["parameter"]): r for r in result["table"]}
    assert table[("pe-rlhf", "full")]["success_rate"]["mean"] == pytest.approx(0.5)
    ablated = table[("pe-rlhf", "ablated")]
    assert (ablated["seeds"], ablated["cells"]) == (2, 3)  # the unfinished seed counts as a cell, not a seed
    assert ablated["success_rate"]["mean"] == pytest.approx(0.25)
    assert ablated["success_rate"]["lo"] <= 0.25 <= ablated["success_rate"]["hi"]
    delta = result["paired"]["success_rate"][("pe-rlhf", "professional", "ablated")]
    assert delta["n"] == 2 and delta["mean"] == pytest.approx(-0.25)  # seed 0: 0.1 - 0.4, seed 1: 0.4 - 0.6
    text = (tmp_path / "out" / "summary.md").read_text()
    assert text.startswith("# T") and "Paired by seed against `full`" in text and "2/3" in text
    assert (tmp_path / "out" / "summary.png").stat().st_size > 1000
    assert len(list(csv.DictReader(open(tmp_path / "out" / "summary.csv")))) == 3


def test_paired_differences_use_only_seeds_both_rows_finished(tmp_path):
    rows = read_rows(_write(tmp_path / "c.csv", [_row("full", 0, 0.5), _row("x", 0, 0.7), _row("x", 1, 0.1)]))
    (stats,) = paired_differences(rows, "success_rate", "full").values()
    assert stats["n"] == 1 and stats["mean"] == pytest.approx(0.2)


def test_a_method_without_the_reference_row_pairs_with_the_one_method_that_has_it(tmp_path):
    """HACO as the "none" row of the physics ablation: paired with PE-RLHF's idm+mobil row, seed by seed."""
    rows = read_rows(_write(tmp_path / "d.csv", [_row("idm+mobil", 0, 0.4), _row("idm+mobil", 1, 0.5),
                                                  _row("none", 0, 0.6, method="haco"),
                                                  _row("none", 1, 0.8, method="haco")]))
    stats = paired_differences(rows, "success_rate", "idm+mobil")[("haco", "professional", "none")]
    assert stats["n"] == 2 and stats["mean"] == pytest.approx(0.25)


def test_an_unknown_metric_or_a_missing_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such cells.csv"):
        summarise_cells([tmp_path / "none.csv"], tmp_path / "out", ["success_rate"])
    a = _write(tmp_path / "a.csv", [_row("full", 0, 0.4)])
    with pytest.raises(ValueError, match=r"metrics \['speed'\]: not among"):
        summarise_cells([a], tmp_path / "out", ["speed"])


def test_a_source_can_keep_only_some_methods_so_a_table_takes_each_method_from_its_own_sweep(tmp_path):
    """Table 1's RLHF rows: HG-DAgger from one sweep, HACO from another that also ran an older PE-RLHF."""
    old = _write(tmp_path / "old.csv", [_row("-", 0, 0.6, method="haco"), _row("-", 0, 0.1, method="pe-rlhf")])
    new = _write(tmp_path / "new.csv", [_row("-", 0, 0.2, method="hg-dagger"), _row("-", 1, 0.4, method="hg-dagger")])
    rows = read_rows([f"{old}:haco", new])
    assert sorted((r["method"], r["seed"], r["success_rate"]) for r in rows) == [
        ("haco", 0, 0.6), ("hg-dagger", 0, 0.2), ("hg-dagger", 1, 0.4)]
    with pytest.raises(FileNotFoundError, match="gone.csv: no such cells.csv"):
        read_rows([f"{tmp_path / 'gone.csv'}:haco"])


def test_one_numeric_parameter_is_read_as_an_axis_and_anything_else_is_not(tmp_path):
    """A sensitivity (epsilon_select=-0.5 ... 3) plots as lines against the value; named variants do not."""
    rows = [_row("epsilon_select=-0.5", 0, 0.4), _row("epsilon_select=3", 0, 0.2, mentor="amateur"),
            _row("-", 0, 0.5, method="idm-mobil", mentor="-")]
    result = summarise_cells([_write(tmp_path / "e.csv", rows)], tmp_path / "out", ["success_rate"])
    assert numeric_parameters(result["table"]) == ("epsilon_select", {"epsilon_select=-0.5": -0.5,
                                                                       "epsilon_select=3": 3.0})
    assert (tmp_path / "out" / "summary.png").stat().st_size > 1000
    assert numeric_parameters([{"mentor": "professional", "parameter": "full"}]) is None
    assert numeric_parameters([{"mentor": "m", "parameter": "a=1"}, {"mentor": "m", "parameter": "b=2"}]) is None
    assert numeric_parameters([{"mentor": "m", "parameter": "a=x"}]) is None
