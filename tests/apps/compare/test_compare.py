"""``pe-rlhf compare``: Table 1 from run folders. Exact means / stds from hand-made run folders, label
inference, the evaluation-only row, errors that name the path, the outputs, and one end-to-end on real
smoke runs (PE-RLHF x 2 seeds, HACO, BC)."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import pytest
import yaml

from pe_rlhf.apps.cli import main as cli_main
from pe_rlhf.apps.compare import CompareError, collect_rows, infer_label, write_comparison
from pe_rlhf.apps.compare.rows import load_run

pytestmark = pytest.mark.usefixtures("one_thread_module")

# the paper's Table 1 header (spec section 7), after its "method" column
PAPER_COLUMNS = ["takeover data", "train safety viol.", "test return", "success", "test safety", "distance m",
                 "velocity km/h", "overtakes"]
HEADER = ["method", "seeds", "takeover data", "total data", "training time (min)", "train safety viol.", "test return",
          "success", "test safety", "distance m", "velocity km/h", "overtakes"]
TEST_KEYS = ("episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
             "overtake_count")


def _proxy_q_config(seed=0, physics=True, disturbance=None, mentor="professional", objective="paper") -> dict:
    cfg = {"seed": seed, "profile": "cpu", "mentor": {"name": mentor, "seed": seed},
           "physics": {"enabled": physics}, "loss": {"objective": objective},
           "eval": {"episodes": 20, "split": "test"}}
    if disturbance is not None:
        cfg["disturbance"] = {"enabled": disturbance}
    return cfg


def _final(test: dict[str, float], training: dict | None = None, **extra) -> dict:
    final = {k: {"mean": v, "std": 0.5} for k, v in test.items()}
    return {**final, "episodes": 20, "training": training, **extra}


def make_run(directory: Path, config: dict | None, final: dict | None, rows: list[dict] | None = None) -> Path:
    """A run folder: ``config.yaml``, ``final_eval.json`` and ``metrics.csv`` (each when given)."""
    directory.mkdir(parents=True, exist_ok=True)
    if config is not None:
        (directory / "config.yaml").write_text(yaml.safe_dump(config))
    if final is not None:
        (directory / "final_eval.json").write_text(json.dumps(final))
    if rows:
        with open(directory / "metrics.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return directory


def _curve(steps: int, usage: float, wall: float, violations: float) -> list[dict]:
    """Two logged rows ending at ``steps`` env steps with the given totals."""
    half = steps // 2
    return [{"step": half, "env_steps": half, "wall_time": wall / 2, "train/safety_violations_total": violations / 2,
             "train/takeover_rate": 0.9, "train/takeover_data_usage": usage},
            {"step": steps, "env_steps": steps, "wall_time": wall, "train/safety_violations_total": violations,
             "train/takeover_rate": 0.5, "train/takeover_data_usage": usage}]


# seed -> (takeover usage, wall s, train violations, test values in TEST_KEYS order)
HACO_SEEDS = {0: (0.2, 120.0, 4.0, (100.0, 0.5, 0.2, 50.0, 30.0, 1.0)),
              1: (0.4, 240.0, 8.0, (200.0, 0.7, 0.4, 70.0, 40.0, 3.0))}


@pytest.fixture
def haco_dir(tmp_path) -> Path:
    """``haco/seed_0``, ``haco/seed_1`` (HACO, 1000 env steps each) and an unfinished ``haco/seed_2``."""
    root = tmp_path / "haco"
    for seed, (usage, wall, violations, test) in HACO_SEEDS.items():
        make_run(root / f"seed_{seed}", _proxy_q_config(seed, physics=False),
                 _final(dict(zip(TEST_KEYS, test)), {"frames": 1000.0, "safety_violations": violations}),
                 _curve(1000, usage, wall, violations))
    make_run(root / "seed_2", _proxy_q_config(2, physics=False), None)  # still training
    return root


def _eval_json(path: Path, policy="idm-mobil", success=0.3) -> Path:
    values = dict(zip(TEST_KEYS, (206.3, success, 0.49, 108.56, 19.78, 0.0)))
    path.write_text(json.dumps(_final(values, None, policy=policy, seeds=list(range(1000, 1050)), episodes=50)))
    return path


def _md_rows(md: str) -> dict[str, list[str]]:
    lines = [line for line in md.splitlines() if line.startswith("| ")]
    return {cells[0]: cells for cells in ([c.strip() for c in line.strip("|").split("|")] for line in lines[1:])}


def _csv(path: Path) -> dict[str, dict[str, str]]:
    with open(path) as f:
        return {r["method"]: r for r in csv.DictReader(f)}


# -- numbers -------------------------------------------------------------------------------------------
def test_mean_and_population_std_over_seeds_exactly(haco_dir, tmp_path):
    ev = _eval_json(tmp_path / "idm.json")
    paths, md, notes = write_comparison(tmp_path / "out", runs=[f"HACO={haco_dir}"], evaluations=[f"={ev}"])
    assert notes == [f"skipped unfinished run {haco_dir / 'seed_2'} (no final_eval.json)"]
    row = _md_rows(md)["HACO"]
    # two seeds: the 95% bootstrap CI of the mean is [min, max] = mean -/+ the population std
    assert row == ["HACO", "2", "0.30 [0.20, 0.40]", "1000 [1000, 1000]", "3.0 [2.0, 4.0]", "6.00 [4.00, 8.00]",
                   "150.00 [100.00, 200.00]", "0.60 [0.50, 0.70]", "0.30 [0.20, 0.40]", "60.00 [50.00, 70.00]",
                   "35.00 [30.00, 40.00]", "2.00 [1.00, 3.00]"]
    table = _csv(paths["table_csv"])
    haco = table["HACO"]
    assert (haco["kind"], haco["seeds"]) == ("trained", "2")
    expected = {"takeover_data_usage": (0.3, 0.1), "total_data": (1000, 0), "train_minutes": (3.0, 1.0),
                "train_safety_violations": (6.0, 2.0), "episodic_return": (150.0, 50.0), "success_rate": (0.6, 0.1),
                "safety_violation": (0.3, 0.1), "travel_distance": (60.0, 10.0), "travel_velocity": (35.0, 5.0),
                "overtake_count": (2.0, 1.0)}
    for key, (mean, std) in expected.items():
        assert math.isclose(float(haco[f"{key}_mean"]), mean) and math.isclose(float(haco[f"{key}_std"]), std,
                                                                                abs_tol=1e-12), key
        assert math.isclose(float(haco[f"{key}_lo"]), mean - std, abs_tol=1e-9), key
        assert math.isclose(float(haco[f"{key}_hi"]), mean + std, abs_tol=1e-9), key
    assert haco["sources"] == f"{haco_dir / 'seed_0'};{haco_dir / 'seed_1'}"


def test_evaluation_row_has_test_columns_only_and_comes_first(haco_dir, tmp_path):
    ev = _eval_json(tmp_path / "idm-mobil_test.json")
    paths, md, _ = write_comparison(tmp_path / "out", runs=[str(haco_dir)], evaluations=[str(ev)], plot=False)
    rows = _md_rows(md)
    assert list(rows) == ["IDM-MOBIL", "HACO"]  # the paper's order, labels inferred
    assert rows["IDM-MOBIL"] == ["IDM-MOBIL", "1", "—", "—", "—", "—", "206.30", "0.30", "0.49", "108.56",
                                 "19.78", "0.00"]
    idm = _csv(paths["table_csv"])["IDM-MOBIL"]
    assert idm["kind"] == "evaluation"
    for key in ("takeover_data_usage", "total_data", "train_minutes", "train_safety_violations"):
        assert math.isnan(float(idm[f"{key}_mean"])) and idm[f"{key}_mean"].lower() == "nan", key
    assert float(idm["success_rate_mean"]) == 0.3
    assert "learning_curves" not in paths and not (tmp_path / "out" / "learning_curves.png").exists()


def test_baseline_training_totals_and_demonstrations(tmp_path):
    """BC (offline): no env steps, its demonstrations are its data (takeover data = their share, 1.0);
    HG-DAgger: env steps + demonstrations, takeovers from the log; SAC-RS: no mentor data (—)."""
    test = dict(zip(TEST_KEYS, (1.0, 0.0, 0.0, 5.0, 1.0, 0.0)))
    make_run(tmp_path / "bc", {"method": "bc", "seed": 0, "data": {"mentor": "professional"}},
             _final(test, {"env_steps": 0, "safety_violations": 0.0, "demo_steps": 200.0,
                           "demo_safety_violations": 2.0, "mentor_data_share": 1.0, "wall_time_s": 30.0},
                    method="BC"),
             [{"step": 100, "env_steps": 0, "wall_time": 30.0, "train/safety_violations_total": 0.0}])
    make_run(tmp_path / "hgd", {"method": "hg_dagger", "seed": 0, "mentor": {"name": "professional"}},
             _final(test, {"env_steps": 300, "safety_violations": 1.0, "demo_steps": 200.0,
                           "demo_safety_violations": 0.0, "takeover_data_usage": 0.4, "mentor_data_share": 1.0}),
             [{"step": 300, "env_steps": 300, "wall_time": 60.0, "train/safety_violations_total": 1.0,
               "train/takeover_data_usage": 0.4}])
    make_run(tmp_path / "sac", {"method": "sac_rs", "seed": 0},
             _final(test, {"env_steps": 300, "safety_violations": 3.0, "wall_time_s": 90.0}, method="SAC-RS"))
    _, md, _ = write_comparison(tmp_path / "out", runs=[str(tmp_path / m) for m in ("bc", "hgd", "sac")], plot=False)
    rows = _md_rows(md)
    assert list(rows) == ["SAC-RS", "BC", "HG-DAgger"]
    assert rows["BC"][2:6] == ["1.00", "200", "0.5", "2.00"]
    assert rows["HG-DAgger"][2:6] == ["0.40", "500", "1.0", "1.00"]
    assert rows["SAC-RS"][2:6] == ["—", "300", "1.5", "3.00"]  # no metrics.csv: the training totals


def test_offline_row_is_a_dotted_level_at_its_final_test_value(tmp_path, monkeypatch):
    """BC logs no env steps, so the test panels show its final value as a dotted level across the axis;
    a trained row with env steps gets a dot at its last step instead."""
    import matplotlib.pyplot as plt

    from pe_rlhf.apps.compare.plots import plot_learning_curves

    make_run(tmp_path / "bc", {"method": "bc", "seed": 0, "data": {"mentor": "professional"}},
             _final(dict(zip(TEST_KEYS, (1.0, 0.25, 0.0, 5.0, 1.0, 0.0))), {"env_steps": 0}, method="BC"),
             [{"step": 100, "env_steps": 0, "wall_time": 30.0}])
    make_run(tmp_path / "hgd", {"method": "hg_dagger", "seed": 0, "mentor": {"name": "professional"}},
             _final(dict(zip(TEST_KEYS, (1.0, 0.75, 0.0, 5.0, 1.0, 0.0))), {"env_steps": 300}),
             [{"step": 300, "env_steps": 300, "wall_time": 60.0, "train/takeover_data_usage": 0.4}])
    rows, _ = collect_rows([str(tmp_path / "bc"), str(tmp_path / "hgd")])
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure the function would close
    plot_learning_curves(tmp_path / "curves.png", rows)
    success_axis = figures[0].axes[0]
    assert success_axis.get_title() == "test success rate"
    dotted = [line for line in success_axis.lines if line.get_linestyle() == ":"]
    assert len(dotted) == 1 and list(dotted[0].get_ydata()) == [0.25, 0.25]
    dots = [line for line in success_axis.lines if line.get_marker() == "o"]
    assert len(dots) == 1 and list(dots[0].get_xdata()) == [300.0] and list(dots[0].get_ydata()) == [0.75]


# -- labels --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("config, final, label", [
    (_proxy_q_config(), {}, "PE-RLHF"),
    (_proxy_q_config(physics=False), {}, "HACO"),
    (_proxy_q_config(physics=False, disturbance=True), {}, "HAIM-DRL"),
    (_proxy_q_config(physics=False, disturbance=False), {}, "HACO"),
    (_proxy_q_config(physics=False, objective="proxy_value"), {}, "PVP"),
    (_proxy_q_config(mentor="amateur"), {}, "PE-RLHF (amateur)"),
    ({"method": "sac_lag", "seed": 0}, {"method": "SAC-Lag"}, "SAC-Lag"),
    ({"method": "hg_dagger", "mentor": {"name": "professional"}}, {}, "HG-DAgger"),  # from config.yaml alone
    ({"method": "bc", "data": {"mentor": "amateur"}}, {"method": "BC"}, "BC (amateur)"),
])
def test_label_inferred_from_config(tmp_path, config, final, label):
    run = make_run(tmp_path / "run", config, _final({"success_rate": 0.5}, **final))
    assert infer_label(load_run(run)) == label


@pytest.mark.parametrize("config, final, label", [
    # the recorded registry name decides, whatever the switches say
    ({"algorithm": "haco", **_proxy_q_config(physics=True)}, {"algorithm": "haco"}, "HACO"),
    ({"algorithm": "haim-drl", **_proxy_q_config(mentor="amateur")}, {}, "HAIM-DRL (amateur)"),  # config.yaml alone
    (None, {"algorithm": "sac-lag"}, "SAC-Lag"),  # final_eval.json alone
    ({"algorithm": "bc", "method": "bc", "data": {"mentor": "amateur"}}, {"algorithm": "bc", "method": "BC"},
     "BC (amateur)"),
    ({"algorithm": "pe-rlhf", **_proxy_q_config(disturbance=True)}, {"algorithm": "pe-rlhf"}, "PE-RLHF+disturbance"),
    ({"algorithm": "pe-rlhf", **_proxy_q_config(physics=True)}, {}, "PE-RLHF"),  # no guess to fail
])
def test_label_read_from_the_recorded_method(tmp_path, config, final, label):
    run = make_run(tmp_path / "run", config, _final({"success_rate": 0.5}, **final))
    assert infer_label(load_run(run)) == label


def test_label_inference_failures_name_the_file(tmp_path):
    mixed = make_run(tmp_path / "mixed", _proxy_q_config(physics=False, disturbance=True, objective="proxy_value"),
                     _final({"success_rate": 0.5}))  # HAIM-DRL's disturbance critic is a PERLHFLoss term
    with pytest.raises(CompareError, match=re.escape(str(mixed / "config.yaml"))):
        infer_label(load_run(mixed))
    bare = make_run(tmp_path / "bare", None, _final({"success_rate": 0.5}))
    with pytest.raises(CompareError, match=re.escape(f"{bare}: cannot tell the method")):
        collect_rows([str(bare)])
    rows, _ = collect_rows([f"Mine={bare}"])  # a given label needs no inference
    assert rows[0].label == "Mine"


def test_glob_groups_seed_folders_and_tells_equal_labels_apart(tmp_path):
    for name, seeds in (("lanes", (0, 1)), ("lanes_eps0", (0,))):
        for seed in seeds:
            make_run(tmp_path / "runs" / name / f"seed_{seed}", _proxy_q_config(seed), _final({"success_rate": 0.5}))
    _eval_json(tmp_path / "runs" / "idm.json")
    rows, _ = collect_rows(globs=[str(tmp_path / "runs" / "*")])
    assert [(r.label, len(r.sources), r.kind) for r in rows] == [
        ("IDM-MOBIL", 1, "evaluation"), ("PE-RLHF (lanes)", 2, "trained"), ("PE-RLHF (lanes_eps0)", 1, "trained")]
    ordered, _ = collect_rows(globs=[str(tmp_path / "runs" / "*")], order=["PE-RLHF (lanes_eps0)", "IDM-MOBIL"])
    assert [r.label for r in ordered] == ["PE-RLHF (lanes_eps0)", "IDM-MOBIL", "PE-RLHF (lanes)"]


def test_glob_groups_sweep_cells_by_seed_suffix(tmp_path):
    """A sweep folder's cells (``NAME__sSEED``): one row per NAME; an evaluation-only cell (its final_eval.json
    names a policy, its config.yaml is the recipe's) is an evaluation row."""
    sweep = tmp_path / "sweep"
    for name in ("pe-rlhf__eps=0__s0", "pe-rlhf__eps=0__s1", "pe-rlhf__eps=1__s0"):
        make_run(sweep / name, _proxy_q_config(), _final({"success_rate": 0.5}))
    make_run(sweep / "idm-mobil__s0", _proxy_q_config(), _final({"success_rate": 0.3}, policy="idm-mobil"))
    (sweep / "logs").mkdir()
    (sweep / "cells.csv").write_text("cell\n")
    rows, notes = collect_rows(globs=[str(sweep / "*")])
    assert [(r.label, len(r.sources), r.kind) for r in rows] == [
        ("IDM-MOBIL", 1, "evaluation"), ("PE-RLHF (pe-rlhf__eps=0)", 2, "trained"),
        ("PE-RLHF (pe-rlhf__eps=1)", 1, "trained")]
    assert notes == [f"skipped {sweep / 'logs'}: no final_eval.json here nor in its subfolders"]


# -- errors --------------------------------------------------------------------------------------------
def test_errors_name_the_bad_path(tmp_path, capsys):
    unfinished = make_run(tmp_path / "unfinished", _proxy_q_config(), None)
    with pytest.raises(CompareError, match=re.escape(f"{unfinished}: no final_eval.json")):
        collect_rows([f"X={unfinished}"])
    with pytest.raises(CompareError, match=re.escape(f"{tmp_path / 'missing'}: no such run folder")):
        collect_rows([f"X={tmp_path / 'missing'}"])
    broken = make_run(tmp_path / "broken", _proxy_q_config(), None)
    (broken / "final_eval.json").write_text("{not json")
    with pytest.raises(CompareError, match=re.escape(f"{broken / 'final_eval.json'}: not valid JSON")):
        collect_rows([f"X={broken}"])
    not_eval = tmp_path / "other.json"
    not_eval.write_text(json.dumps({"hello": 1}))
    with pytest.raises(CompareError, match=re.escape(f"{not_eval}: not an evaluation summary")):
        collect_rows(evaluations=[f"IDM={not_eval}"])
    with pytest.raises(CompareError, match="given twice: A"):
        collect_rows(evaluations=[f"A={_eval_json(tmp_path / 'a.json')}", f"A={tmp_path / 'a.json'}"])
    with pytest.raises(CompareError, match="--order: no row labelled 'B'"):
        collect_rows(evaluations=[f"A={tmp_path / 'a.json'}"], order=["B"])
    with pytest.raises(CompareError, match="matched nothing"):
        collect_rows(globs=[str(tmp_path / "nothing*")])
    with pytest.raises(SystemExit) as exit_info:  # the CLI: a usage error naming the path, no traceback
        cli_main(["compare", "--row", f"X={broken}", "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2 and str(broken / "final_eval.json") in capsys.readouterr().err


# -- outputs -------------------------------------------------------------------------------------------
def test_cli_writes_markdown_csv_png_in_paper_column_order(haco_dir, tmp_path, capsys):
    make_run(tmp_path / "pe" / "seed_0", _proxy_q_config(0), _final(dict(zip(TEST_KEYS, [1.0] * 6)),
                                                                    {"frames": 1000.0}),
             [{**r, "eval/success_rate_mean": 0.1 * i} for i, r in enumerate(_curve(1000, 0.3, 60.0, 2.0))])
    ev = _eval_json(tmp_path / "idm.json")
    out = tmp_path / "out"
    assert cli_main(["compare", "--row", f"HACO={haco_dir}", "--row", str(tmp_path / "pe"), "--eval", f"IDM-MOBIL={ev}",
                     "--out", str(out), "--order", "PE-RLHF,HACO", "--title", "T1"]) == 0
    captured = capsys.readouterr()
    header = [c.strip() for c in captured.out.splitlines()[0].strip("|").split("|")]
    assert header == HEADER
    assert [c for c in header if c in PAPER_COLUMNS] == PAPER_COLUMNS  # the paper's columns in its order
    assert "skipped unfinished run" in captured.err
    md = (out / "table.md").read_text()
    assert md.startswith("# T1\n") and "![learning curves](learning_curves.png)" in md
    assert "## Test success at each periodic evaluation" in md  # PE-RLHF logged eval/success_rate_mean
    assert "- **PE-RLHF**: 500 0.00 · 1K 0.10" in md and "- **HACO**:" not in md  # HACO logged no evaluation
    assert list(_md_rows(md)) == ["PE-RLHF", "HACO", "IDM-MOBIL"]
    assert _md_rows(md) == _md_rows(captured.out)  # stdout prints the same table
    png = out / "learning_curves.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert list(_csv(out / "table.csv")) == ["PE-RLHF", "HACO", "IDM-MOBIL"]


def test_group_figures_hold_their_rows_and_the_reference_levels(haco_dir, tmp_path, capsys, monkeypatch):
    """``--group rlhf=HACO`` draws learning_curves_rlhf.png with HACO and IDM-MOBIL only; table.md embeds it."""
    import matplotlib.pyplot as plt

    make_run(tmp_path / "pe" / "seed_0", _proxy_q_config(0), _final(dict(zip(TEST_KEYS, [1.0] * 6)),
                                                                    {"frames": 1000.0}), _curve(1000, 0.3, 60.0, 2.0))
    ev = _eval_json(tmp_path / "idm.json")
    out = tmp_path / "out"
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    assert cli_main(["compare", "--row", f"HACO={haco_dir}", "--row", f"PE-RLHF={tmp_path / 'pe'}",
                     "--eval", f"IDM-MOBIL={ev}", "--group", "rlhf=HACO", "--out", str(out)]) == 0
    md = (out / "table.md").read_text()
    assert "![learning curves](learning_curves.png)" in md and "![learning curves rlhf](learning_curves_rlhf.png)" in md
    assert (out / "learning_curves_rlhf.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    full, group = figures
    assert group.get_suptitle().startswith("rlhf: ") and not full.get_suptitle().startswith("rlhf")
    def legend(fig):
        return [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend(full) == ["IDM-MOBIL", "HACO", "PE-RLHF"] and legend(group) == ["IDM-MOBIL", "HACO"]


def test_group_specs_are_checked_before_anything_is_written(haco_dir, tmp_path, capsys):
    from pe_rlhf.apps.compare import parse_group, select_group

    assert parse_group(" rl = SAC-RS, PPO-RS ,") == ("rl", ["SAC-RS", "PPO-RS"])
    for bad in ("rl", "=HACO", "r l=HACO", "rl="):
        with pytest.raises(CompareError, match=re.escape(f"--group {bad!r}")):
            parse_group(bad)
    rows, _ = collect_rows([f"HACO={haco_dir}"])
    with pytest.raises(CompareError, match="no row labelled 'SAC-RS'; rows: HACO"):
        select_group(rows, ["SAC-RS"])
    with pytest.raises(SystemExit) as exit_info:  # the CLI: a usage error, and no output folder
        cli_main(["compare", "--row", f"HACO={haco_dir}", "--group", "rl=SAC-RS", "--out", str(tmp_path / "o")])
    assert exit_info.value.code == 2 and "no row labelled 'SAC-RS'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_learning_curve_mean_and_band_over_seeds(haco_dir):
    from pe_rlhf.apps.compare.plots import row_curve

    rows, _ = collect_rows([str(haco_dir)])
    steps, mean, low, high = row_curve(rows[0], "train/safety_violations_total")
    assert steps.tolist() == [500, 1000]
    assert mean.tolist() == [3.0, 6.0] and low.tolist() == [2.0, 4.0] and high.tolist() == [4.0, 8.0]
    steps, mean, *_ = row_curve(rows[0], "train/takeover_rate", window=2)  # moving average over 2 rows
    assert mean.tolist() == [0.9, 0.7]
    assert row_curve(rows[0], "eval/success_rate_mean") is None  # no periodic evaluation logged


# -- end to end on real smoke runs --------------------------------------------------------------------
@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory) -> Path:
    """``runs/pe/seed_{0,1}`` (PE-RLHF), ``runs/haco/seed_0`` and ``runs/bc`` from the real recipes' smoke
    profiles with tiny budgets (once per module)."""
    from pe_rlhf.algorithms.baselines import main as baseline_main
    from _scripts import load_pe_rlhf_recipe

    recipe = load_pe_rlhf_recipe()
    root = tmp_path_factory.mktemp("runs")
    tiny = ["profile=smoke", "eval.video=false", "collector.total_frames=200"]
    for seed in (0, 1):
        recipe.main([*tiny, f"seed={seed}", "--out", str(root / "pe" / f"seed_{seed}")])
    recipe.main([*tiny, "physics.enabled=false", "loss.objective=paper", "--out", str(root / "haco" / "seed_0")])
    baseline_main("bc", ["profile=smoke", "optim.updates=50", "--out", str(root / "bc")])
    return root


def test_end_to_end_on_smoke_runs(smoke_runs, tmp_path, capsys):
    ev = _eval_json(tmp_path / "idm-mobil_test.json")
    assert cli_main(["compare", "--glob", str(smoke_runs / "*"), "--eval", str(ev), "--out", str(tmp_path / "t")]) == 0
    rows = _md_rows(capsys.readouterr().out)
    assert list(rows) == ["IDM-MOBIL", "BC", "HACO", "PE-RLHF"]
    table = _csv(tmp_path / "t" / "table.csv")
    finals = [json.loads((smoke_runs / "pe" / f"seed_{s}" / "final_eval.json").read_text()) for s in (0, 1)]
    for key in TEST_KEYS:  # the test columns: mean and population std of the seeds' final_eval means
        values = [f[key]["mean"] for f in finals]
        mean = sum(values) / 2
        assert math.isclose(float(table["PE-RLHF"][f"{key}_mean"]), mean, abs_tol=1e-9), key
        assert math.isclose(float(table["PE-RLHF"][f"{key}_std"]), abs(values[0] - mean), abs_tol=1e-9), key
    assert table["PE-RLHF"]["seeds"] == "2" and float(table["PE-RLHF"]["total_data_mean"]) == 200
    assert 0 < float(table["HACO"]["takeover_data_usage_mean"]) <= 1
    assert rows["BC"][2:4] == ["1.00", "200"]  # all of BC's data is the mentor's 200 recorded steps
    assert (tmp_path / "t" / "learning_curves.png").stat().st_size > 10_000


def test_smoke_runs_record_their_method_and_old_run_folders_are_labelled_as_before(smoke_runs, tmp_path):
    """Every run writes its registry name into final_eval.json and config.yaml; a folder from before that
    record (both removed) gets the label the switches or the baseline's ``method`` give, the same one."""
    import shutil

    for run, name, label in ((smoke_runs / "pe" / "seed_0", "pe-rlhf", "PE-RLHF"),
                             (smoke_runs / "haco" / "seed_0", "haco", "HACO"), (smoke_runs / "bc", "bc", "BC")):
        final = json.loads((run / "final_eval.json").read_text())
        config = yaml.safe_load((run / "config.yaml").read_text())
        assert final["algorithm"] == config["algorithm"] == name
        assert infer_label(load_run(run)) == label
        old = shutil.copytree(run, tmp_path / run.name / name)
        final.pop("algorithm")
        config.pop("algorithm")
        (old / "final_eval.json").write_text(json.dumps(final))
        (old / "config.yaml").write_text(yaml.safe_dump(config))
        assert infer_label(load_run(old)) == label
