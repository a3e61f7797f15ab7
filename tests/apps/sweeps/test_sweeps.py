"""Sweeps: grid expansion and naming, config errors naming the field, bookkeeping (finished cells are not
rerun, crashed ones resume), summary aggregation from synthetic cell folders, and a 2-cell sweep on local
Ray and as local processes with tiny budgets."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import pytest
from _scripts import load_script

from pe_rlhf.apps.sweeps import SweepConfigError, check_cell_configs, expand, load_sweep, parse_sweep, run_sweep
from pe_rlhf.apps.sweeps.cells import CELL_FILE, FINAL_EVAL, SHIELDED_EVAL, attempt_argv, check_folder, plan, write_record
from pe_rlhf.apps.sweeps.execution import run_cells
from pe_rlhf.apps.sweeps.summary import aggregate, cell_rows, mean_std, write_summary

ROOT = Path(__file__).resolve().parents[3]
SMOKE = ["profile=smoke"]


def _spec(**changes):
    raw = {"name": "t", "base": SMOKE,
           "methods": ["pe-rlhf", {"name": "haco", "parameters": False}, "idm-mobil"],
           "mentors": ["professional", {"label": "collapse", "name": "collapsing", "kwargs": {"switch_step": 100}}],
           "parameters": {"selector.epsilon_select": [0.25, 1]}, "seeds": [0, 1]}
    raw.update(changes)
    return parse_sweep({k: v for k, v in raw.items() if v is not None})


# -- grid ----------------------------------------------------------------------------------------
def test_grid_expansion_names_and_overrides():
    cells = expand(_spec())
    names = [c.name for c in cells]
    assert names == [c.name for c in expand(_spec())]  # deterministic
    assert len(names) == len(set(names)) == 2 * 2 * 2 + 2 * 2 + 2  # pe-rlhf m x p x s, haco m x s, idm-mobil s
    assert names[:3] == ["pe-rlhf__professional__epsilon_select=0.25__s0",
                         "pe-rlhf__professional__epsilon_select=0.25__s1",
                         "pe-rlhf__professional__epsilon_select=1__s0"]
    assert names[-3:] == ["haco__collapse__s1", "idm-mobil__s0", "idm-mobil__s1"]
    by_name = {c.name: c for c in cells}
    cell = by_name["pe-rlhf__collapse__epsilon_select=1__s1"]
    assert cell.overrides == ("profile=smoke", "mentor.name=collapsing", "mentor.kwargs.switch_step=100",
                              "selector.epsilon_select=1", "seed=1")
    assert (cell.method.name, cell.mentor, cell.parameter, cell.seed) == ("pe-rlhf", "collapse", "epsilon_select=1", 1)
    haco = by_name["haco__professional__s0"]  # recipes/haco: PE-RLHF's loop without physics, the paper's loss
    assert haco.overrides == ("profile=smoke", "mentor.name=professional", "seed=0") and haco.method.recipe == "haco"
    idm = by_name["idm-mobil__s1"]
    assert idm.overrides == ("profile=smoke", "seed=1") and idm.method.recipe == "evaluate"
    check_cell_configs(cells)  # every override is a valid recipe config
    assert {c.shield for c in cells} == {None}


def test_a_shielded_sweep_shields_only_its_trained_cells():
    from pe_rlhf.runtime.recipe import SHIELDED_EVAL as RECIPES_FILE
    from pe_rlhf.transforms.shield import DEFAULT_THRESHOLD

    assert SHIELDED_EVAL == RECIPES_FILE  # the sweep reads what `train.py --shield` writes

    cells = expand(_spec(shield=0.25))
    assert {c.name.split("__")[0]: c.shield for c in cells} == {"pe-rlhf": 0.25, "haco": 0.25, "idm-mobil": None}
    assert _spec(shield=True).shield == DEFAULT_THRESHOLD and _spec(shield=False).shield is None
    assert expand(_spec(shield=0))[0].shield == 0.0  # a threshold of 0 s is a shield too
    # the threshold is not the cell's training: a folder trained without it is still the cell's
    assert cells[0].record()["shield"] == 0.25 and cells[0].overrides == expand(_spec())[0].overrides


def test_variants_cross_parameters_and_baselines_map_to_their_recipe():
    spec = _spec(methods=["pe-rlhf", "sac-rs"], mentors=["amateur"], variants={"a": ["optim.lr=0.001"], "b": []},
                 parameters={"loss.gamma": [0.9]}, seeds=[3])
    cells = {c.name: c for c in expand(spec)}
    assert set(cells) == {"pe-rlhf__amateur__a+gamma=0.9__s3", "pe-rlhf__amateur__b+gamma=0.9__s3",
                          "sac-rs__a+gamma=0.9__s3", "sac-rs__b+gamma=0.9__s3"}
    sac = cells["sac-rs__a+gamma=0.9__s3"]
    assert sac.method.recipe == "sac_rs" and sac.overrides == ("profile=smoke", "optim.lr=0.001", "loss.gamma=0.9",
                                                               "seed=3")
    check_cell_configs(list(cells.values()))


def test_named_sweep_configs_load_and_validate():
    counts = {}
    for path in sorted((ROOT / "recipes" / "sweeps").glob("*.yaml")):
        spec = load_sweep(path)
        cells = expand(spec)
        check_cell_configs(cells)
        counts[spec.name] = len(cells)
    assert counts == {"claims": 2 * 2 * 5 + 5, "claims_forecast": 2 * 5,
                      "claims_balanced": 2 * 5, "claims_select": 2 * 5, "claims_amateur": 4 * 5,
                      "claims_collapsing": 4 * 5, "claims_adversarial": 4 * 5,
                      "epsilon_sensitivity": 5 * 2 * 3 + 3, "loss_ablations": 6 * 3, "lower_bound": 4 * 2 * 3 + 3,
                      "mentor_proficiency": 12, "physics_ablation": 9 + 3, "warmup": 2 * 4 * 3,
                      "learner_calibration": 6 * 3, "learner_pvp": 4 * 3, "learner_early_mentor": 2 * 3, "learner_bc": 2 * 3,
                      "claims_learner": 5 * 5,
                      "table1_rlhf": 5 * 3 + 3, "haco_failure_target": 2 * 3}


# -- errors --------------------------------------------------------------------------------------
@pytest.mark.parametrize("changes, field", [
    ({"metric": ["success_rate"]}, "metric"),
    ({"methods": ["pe-rlhf", "pe-rlfh"]}, r"methods\[1\]"),
    ({"methods": [{"name": "x", "recipe": "nope"}]}, r"methods\[0\]\.recipe"),
    ({"methods": [{"name": "x", "method": "haco", "overides": []}]}, r"methods\[0\]\.overides"),
    ({"methods": ["haco", "haco"]}, "methods"),
    ({"mentors": [{"name": "amateur", "kwrgs": {}}]}, r"mentors\[0\]\.kwrgs"),
    ({"mentors": ["amateur", "amateur"]}, "mentors"),
    ({"seeds": [0, 0]}, "seeds"),
    ({"seeds": [-1]}, "seeds"),
    ({"parameters": {"selector.epsilon_select": 0.5}}, r"parameters\.selector\.epsilon_select"),
    ({"variants": {"a/b": []}}, r"variants\.a/b"),
    ({"base": ["profile"]}, r"base\[0\]"),
    ({"metrics": ["succes_rate"]}, "metrics"),
    ({"resources": {"num_cpus": 0}}, r"resources\.num_cpus"),
    ({"shield": -0.5}, r"shield=-0\.5 is invalid: a threshold in seconds"),
    ({"shield": "yes"}, "shield='yes'"),
])
def test_bad_sweep_fields_are_named(changes, field):
    with pytest.raises(SweepConfigError, match=field):
        _spec(**changes)


@pytest.mark.parametrize("changes, field", [
    ({"base": ["profile=smoke", "optim.lrr=1"]}, "optim.lrr"),
    ({"mentors": ["professionel"]}, "mentor.name"),
    ({"parameters": {"selector.epsilon_select": ["high"]}}, "selector.epsilon_select"),
    ({"mentors": [{"name": "collapsing", "kwargs": {"switch_at": 5}}]}, r"mentor\.kwargs\.switch_at"),
])
def test_bad_cell_configs_name_the_cell_and_field(changes, field):
    with pytest.raises(SweepConfigError, match=rf"cell pe-rlhf__.*{field}"):
        check_cell_configs(expand(_spec(**changes)))


def test_bad_files(tmp_path):
    with pytest.raises(SweepConfigError, match="not found"):
        load_sweep(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("methods: [pe-rlhf\n")
    with pytest.raises(SweepConfigError, match="not valid YAML"):
        load_sweep(tmp_path / "bad.yaml")
    (tmp_path / "named.yaml").write_text("methods: [pe-rlhf]\nseeds: [0]\n")
    assert load_sweep(tmp_path / "named.yaml").name == "named"


def test_cli_dry_run_and_errors(tmp_path, capsys):
    from pe_rlhf.apps.cli import main

    config = tmp_path / "eps.yaml"
    config.write_text("base: [profile=smoke]\nmethods: [pe-rlhf, idm-mobil]\nmentors: [amateur]\nseeds: [0, 1]\n"
                      "parameters: {selector.epsilon_select: [0, 1.5]}\n")
    assert main(["sweep", str(config), "--dry-run", "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "sweep eps: 6 cells (0 finished, 0 to resume, 6 to run)" in printed
    assert "run      pe-rlhf__amateur__epsilon_select=1.5__s1: pe_rlhf profile=smoke mentor.name=amateur " \
           "selector.epsilon_select=1.5 seed=1" in printed
    assert not (tmp_path / "out").exists()  # a dry run writes nothing
    config.write_text("methods: [pe-rlhf]\nseeds: [0]\nmentors: [{name: amateur, kwargs: {action_noise: 2}}]\n")
    with pytest.raises(SystemExit):
        main(["sweep", str(config), "--dry-run"])
    assert "cell pe-rlhf__amateur__s0" in (err := capsys.readouterr().err) and "action_noise" in err


def test_cli_only_selects_cells_by_name(tmp_path, capsys):
    from pe_rlhf.apps.cli import main

    config = tmp_path / "eps.yaml"
    config.write_text("base: [profile=smoke]\nmethods: [pe-rlhf, haco, idm-mobil]\nseeds: [0, 1]\n")
    assert main(["sweep", str(config), "--dry-run", "--only", "^haco", "--only", "idm", "--out",
                 str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "sweep eps: 4 cells" in printed
    assert "haco__s1" in printed and "idm-mobil__s0" in printed and "pe-rlhf__" not in printed
    with pytest.raises(SystemExit):
        main(["sweep", str(config), "--dry-run", "--only", "amateur"])
    assert "matches none of the 6 cells" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["sweep", str(config), "--dry-run", "--only", "("])
    assert "not a regular expression" in capsys.readouterr().err


# -- bookkeeping ---------------------------------------------------------------------------------
def test_finished_cells_are_skipped_and_crashed_ones_resume(tmp_path):
    cells = expand(_spec(methods=["pe-rlhf"], mentors=None, parameters=None, seeds=[0, 1, 2]))
    write_record(tmp_path, cells[0])
    (tmp_path / cells[0].name / FINAL_EVAL).write_text("{}")
    finished, todo = plan(tmp_path, cells)
    assert [c.name for c in finished] == ["pe-rlhf__s0"] and [c.name for c in todo] == ["pe-rlhf__s1", "pe-rlhf__s2"]
    report = run_cells(cells[:1], tmp_path, progress=False)  # nothing to run: Ray is never started
    assert report.skipped == ["pe-rlhf__s0"] and not report.finished and not report.failed
    # a crashed cell with a complete checkpoint resumes; one without starts over in an emptied folder
    crashed, fresh = tmp_path / cells[1].name, tmp_path / cells[2].name
    for d in (crashed, fresh):
        (d / "checkpoints" / "ckpt_000000100").mkdir(parents=True)
        (d / "config.yaml").write_text("seed: 1\n")
        (d / CELL_FILE).write_text("{}")
    (crashed / "checkpoints" / "ckpt_000000100" / "COMPLETE").write_text("")
    assert attempt_argv(crashed, list(cells[1].overrides)) == (["--resume", str(crashed)], True)
    argv, resumed = attempt_argv(fresh, list(cells[2].overrides))
    assert not resumed and argv == [*cells[2].overrides, "--out", str(fresh)]
    assert [p.name for p in fresh.iterdir()] == [CELL_FILE]
    # a folder made by another config is refused, naming what differs
    other = expand(_spec(methods=["pe-rlhf"], mentors=None, parameters=None, seeds=[0], base=["profile=cpu"]))[0]
    with pytest.raises(SweepConfigError, match="overrides"):
        check_folder(tmp_path, other)
    (tmp_path / cells[0].name / CELL_FILE).unlink()  # someone else's run folder is never emptied
    with pytest.raises(SweepConfigError, match="not made by a sweep"):
        plan(tmp_path, cells)


def test_a_cell_folder_from_before_the_seed_seeded_the_mentor_is_still_the_cells(tmp_path):
    """Cells added ``mentor.seed=<seed>`` until the run's seed seeded the mentor too (issue 43): their folders are
    still the same cells (finished ones summarised, unfinished ones resumed), not another config's."""
    cells = expand(_spec(methods=["pe-rlhf", "idm-mobil"], mentors=None, parameters=None, seeds=[1]))
    for cell in cells:
        write_record(tmp_path, cell)
    record = tmp_path / cells[0].name / CELL_FILE
    saved = json.loads(record.read_text())
    record.write_text(json.dumps({**saved, "overrides": [*saved["overrides"], "mentor.seed=1"]}))
    assert plan(tmp_path, cells) == ([], cells)
    record.write_text(json.dumps({**saved, "overrides": [*saved["overrides"], "mentor.seed=2"]}))
    with pytest.raises(SweepConfigError, match="overrides"):  # another seed's mentor: another config
        check_folder(tmp_path, cells[0])


# -- summary -------------------------------------------------------------------------------------
def _fake_cell(out: Path, cell, success: float | None, violations: float = 0.0, usage: float = 0.0) -> None:
    write_record(out, cell)
    if success is None:
        return
    final = {"success_rate": {"mean": success, "std": 0.0}, "safety_violation": {"mean": 1 - success, "std": 0.0},
             "training": None if not cell.method.trains else {"safety_violations": violations}}
    (out / cell.name / FINAL_EVAL).write_text(json.dumps(final))
    if cell.method.trains:
        with open(out / cell.name / "metrics.csv", "w") as f:
            f.write("step,env_steps,wall_time,train/safety_violations_total,train/takeover_data_usage,"
                    "train/value_takeover_rate,train/takeover_rate\n")
            f.write(f"100,100,1.0,0,0.5,1.0,1.0\n200,200,2.0,{violations},{usage},0.5,0.4\n")


def test_summary_aggregates_seeds_exactly(tmp_path):
    cells = expand(_spec(methods=["pe-rlhf", "idm-mobil"], mentors=["amateur"],
                         parameters={"selector.epsilon_select": [0.5]}, seeds=[0, 1, 2]))
    pe, idm = cells[:3], cells[3:]
    for cell, (success, violations, usage) in zip(pe, [(0.2, 10, 0.3), (0.4, 20, 0.2), (None, 0, 0)]):
        _fake_cell(tmp_path, cell, success, violations, usage)
    for cell in idm:
        _fake_cell(tmp_path, cell, 0.3)
    metrics = ["success_rate", "safety_violation", "train_safety_violations", "takeover_data_usage"]
    table = aggregate(cell_rows(tmp_path, cells), metrics)
    assert [(r["method"], r["mentor"], r["parameter"], r["seeds"], r["cells"]) for r in table] == [
        ("pe-rlhf", "amateur", "epsilon_select=0.5", 2, 3), ("idm-mobil", "-", "-", 3, 3)]
    pe_row, idm_row = table
    # two seeds: every bootstrap resample's mean lies between them, so the 95% CI is [min, max]
    assert pe_row["success_rate"] == {"mean": pytest.approx(0.3), "std": pytest.approx(0.1), "lo": pytest.approx(0.2),
                                      "hi": pytest.approx(0.4), "n": 2}
    assert pe_row["train_safety_violations"] == {"mean": 15.0, "std": 5.0, "lo": 10.0, "hi": 20.0, "n": 2}
    assert pe_row["takeover_data_usage"]["mean"] == pytest.approx(0.25)
    assert idm_row["success_rate"] == {"mean": pytest.approx(0.3), "std": 0.0, "lo": pytest.approx(0.3),
                                       "hi": pytest.approx(0.3), "n": 3}  # seeds agree: a point
    assert idm_row["train_safety_violations"]["n"] == 0  # evaluation only: no training numbers
    assert mean_std([1.0, float("nan"), 3.0]) == {"mean": 2.0, "std": 1.0, "n": 2}

    paths = write_summary(tmp_path, cells, metrics, title="t", plots=True)
    md = (tmp_path / "summary.md").read_text()
    assert ("| pe-rlhf | amateur | epsilon_select=0.5 | 2/3 | 0.30 [0.20, 0.40] | 0.70 [0.60, 0.80] | "
            "15.0 [10.0, 20.0] | 0.25 [0.20, 0.30] |") in md
    assert "| idm-mobil | - | - | 3/3 | 0.30 [0.30, 0.30] | 0.70 [0.70, 0.70] | — | — |" in md
    with open(tmp_path / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    assert float(rows[0]["success_rate_mean"]) == pytest.approx(0.3) and float(rows[0]["success_rate_std"]) == \
        pytest.approx(0.1) and math.isnan(float(rows[1]["train_safety_violations_mean"]))
    assert (float(rows[0]["success_rate_lo"]), float(rows[0]["success_rate_hi"])) == pytest.approx((0.2, 0.4))
    assert math.isnan(float(rows[1]["train_safety_violations_lo"]))
    with open(tmp_path / "cells.csv") as f:
        statuses = [r["status"] for r in csv.DictReader(f)]
    assert statuses == ["finished", "finished", "unfinished", "finished", "finished", "finished"]
    assert {"summary", "value_takeover_rate", "takeover_rate"} <= set(paths)
    assert all(paths[k].stat().st_size > 0 for k in ("summary", "value_takeover_rate", "takeover_rate"))


@pytest.mark.parametrize("axis, joined", [({"parameters": {"selector.epsilon_select": [0.5, 1.0]}}, True),
                                          ({"variants": {"idm_only": [], "mobil_only": []}}, False)])
def test_summary_plot_joins_points_only_along_a_numeric_axis(tmp_path, axis, joined):
    from pe_rlhf.apps.sweeps.plots import _numeric_x, _panel, _pyplot

    plt = _pyplot()

    cells = expand(_spec(**{"methods": ["pe-rlhf"], "mentors": ["professional"], "seeds": [0], "parameters": None,
                            **axis}))
    for cell, success in zip(cells, (0.2, 0.4)):
        _fake_cell(tmp_path, cell, success)
    table = aggregate(cell_rows(tmp_path, cells), ["success_rate"])
    numeric = _numeric_x(cells)
    assert (numeric is not None) == joined  # epsilon: a number line; named variants: categories
    positions = numeric or {c.parameter: float(i) for i, c in enumerate(cells)}
    fig, ax = plt.subplots()
    _panel(ax, table, "success_rate", positions, connect=numeric is not None)
    line = ax.lines[0]
    assert list(line.get_ydata()) == pytest.approx([0.2, 0.4])
    assert (line.get_linestyle() == "-") == joined and (line.get_linestyle() == "None") == (not joined)
    plt.close(fig)


def test_windowed_value_takeover_rate_counts_only_online_batches_in_the_window():
    from pe_rlhf.apps.sweeps.plots import windowed_value_takeover_rate

    # warm-up of 200 steps (2 batches), then batches of 100 steps: takeover steps 50, 20, 0, 40;
    # mentor chosen 40, 10, 0, 10 (the cumulative count below)
    rows = [{"env_steps": 100.0, "train/takeover_rate": 1.0, "train/value_takeover_count": 0.0},
            {"env_steps": 200.0, "train/takeover_rate": 1.0, "train/value_takeover_count": 0.0},
            {"env_steps": 300.0, "train/takeover_rate": 0.5, "train/value_takeover_count": 40.0},
            {"env_steps": 400.0, "train/takeover_rate": 0.2, "train/value_takeover_count": 50.0},
            {"env_steps": 500.0, "train/takeover_rate": 0.0, "train/value_takeover_count": 50.0},
            {"env_steps": 600.0, "train/takeover_rate": 0.4, "train/value_takeover_count": 60.0}]
    assert windowed_value_takeover_rate(rows, warmup_steps=200, window=2) == {
        300.0: pytest.approx(40 / 50), 400.0: pytest.approx(50 / 70), 500.0: pytest.approx(10 / 20),
        600.0: pytest.approx(10 / 40)}
    assert windowed_value_takeover_rate(rows, warmup_steps=200, window=10)[600.0] == pytest.approx(60 / 110)
    # no takeover step in the window: left out
    assert 500.0 not in windowed_value_takeover_rate(rows, warmup_steps=200, window=1)
    assert windowed_value_takeover_rate(rows[:2], warmup_steps=200) == {}


# -- a real sweep on local Ray ---------------------------------------------------------------------
def test_a_sweep_on_local_ray(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    # as run_cells' own local Ray: workers at nice 0 (Ray's default 15 starved the cell behind the other test worker:
    # 64 s for a 100-frame run that takes 11 s alone)
    monkeypatch.setenv("RAY_worker_niceness", "0")
    TINY = load_script("tests/reliability/_runs.py", "reliability_runs").TINY  # the reliability tests' few-second runs

    spec = parse_sweep({"name": "smoke", "base": [*TINY, "collector.total_frames=100"], "seeds": [0],
                        "methods": ["pe-rlhf"],  # one cell: the process backend's test runs pe-rlhf and haco
                        "metrics": ["success_rate", "train_safety_violations", "value_takeover_rate"],
                        "shield": 0.5})  # trained, then evaluated under the shield in the same task
    ray.init(address="local", num_cpus=2,  # a fresh instance, even beside a running `ray start`
             include_dashboard=False, log_to_driver=False)
    try:
        report = run_sweep(spec, tmp_path, progress=False)
        assert report.failed == {} and sorted(report.finished) == ["pe-rlhf__s0"]
        for name in report.finished:
            for output in (FINAL_EVAL, SHIELDED_EVAL, "metrics.csv", "config.yaml", CELL_FILE):
                assert (tmp_path / name / output).is_file(), (name, output)
            assert (tmp_path / "logs" / f"{name}.log").stat().st_size > 0
        for output in ("summary.md", "summary.csv", "cells.csv", "summary.png"):
            assert (tmp_path / output).is_file(), output
        assert "| pe-rlhf | 1/1 |" in (tmp_path / "summary.md").read_text()
        again = run_sweep(spec, tmp_path, progress=False)
        assert again.skipped == ["pe-rlhf__s0"] and not again.finished and not again.failed
    finally:
        ray.shutdown()


# -- the same sweep without Ray -------------------------------------------------------------------
def _tiny_sweep(tmp_path) -> Path:
    tiny = load_script("tests/reliability/_runs.py", "reliability_runs").TINY
    config = tmp_path / "tiny.yaml"
    config.write_text(json.dumps({"name": "tiny", "base": [*tiny, "collector.total_frames=100"], "seeds": [0],
                                  "methods": ["pe-rlhf", "haco"], "metrics": ["success_rate", "value_takeover_rate"]}))
    return config


def test_the_process_backend_runs_the_cells_resumably_without_ray(tmp_path, capsys):
    from pe_rlhf.apps.cli import main

    config, out = _tiny_sweep(tmp_path), tmp_path / "out"
    assert main(["sweep", str(config), "--backend", "processes", "--max-parallel", "2", "--no-progress",
                 "--out", str(out)]) == 0
    assert "0 cells were finished already, 2 finished now, 0 failed" in capsys.readouterr().out
    for name in ("haco__s0", "pe-rlhf__s0"):
        assert json.loads((out / name / FINAL_EVAL).read_text())["episodes"] >= 1
        assert (out / "logs" / f"{name}.log").read_text().startswith("=== ")
    haco = (out / "haco__s0" / "config.yaml").read_text()
    assert haco.startswith("algorithm: haco\n") and "physics:\n  enabled: false" in haco  # recipes/haco ran it
    assert "| pe-rlhf | 1/1 |" in (out / "summary.md").read_text()
    assert main(["sweep", str(config), "--backend", "processes", "--no-progress", "--out", str(out)]) == 0
    assert "2 cells were finished already, 0 finished now, 0 failed" in capsys.readouterr().out
    # the same sweep with a shield: the trained cells get the shielded evaluation alone, not another training
    trained = {name: {f: (out / name / f).read_bytes() for f in (FINAL_EVAL, "metrics.csv")}
               for name in ("haco__s0", "pe-rlhf__s0")}
    config.write_text(json.dumps({**json.loads(config.read_text()), "shield": 0.5,
                                  "metrics": ["success_rate", "shielded_success_rate", "override_share"]}))
    assert main(["sweep", str(config), "--dry-run", "--out", str(out)]) == 0
    assert "2 to evaluate shielded" in capsys.readouterr().out
    assert main(["sweep", str(config), "--backend", "processes", "--no-progress", "--out", str(out)]) == 0
    assert "0 cells were finished already, 2 finished now, 0 failed" in capsys.readouterr().out
    for name, files in trained.items():
        assert {f: (out / name / f).read_bytes() for f in files} == files
        shielded = json.loads((out / name / SHIELDED_EVAL).read_text())
        assert shielded["threshold"] == 0.5 and shielded["episodes"] == 1 and 0 <= shielded["override_share"] <= 1
        log = (out / "logs" / f"{name}.log").read_text()
        assert "trained, the shielded evaluation" in log and "the shield drove" in log
    with open(out / "cells.csv", newline="") as f:
        rows = {r["cell"]: r for r in csv.DictReader(f)}
    assert 0 <= float(rows["pe-rlhf__s0"]["override_share"]) <= 1
    assert float(rows["pe-rlhf__s0"]["shielded_success_rate"]) in (0.0, 1.0)
    assert "| pe-rlhf | 1/1 |" in (out / "summary.md").read_text() and "shielded success" in (out / "summary.md"
                                                                                                 ).read_text()


def test_the_process_backend_stops_cells_at_the_deadline_and_they_run_again_later(tmp_path, capsys):
    from pe_rlhf.apps.cli import main

    config, out = _tiny_sweep(tmp_path), tmp_path / "out"
    assert main(["sweep", str(config), "--backend", "processes", "--max-parallel", "1", "--deadline", "0.5",
                 "--no-progress", "--out", str(out)]) == 1
    printed = capsys.readouterr().out
    assert "0 finished now, 0 failed, 2 stopped" in printed and "stopped: pe-rlhf__s0, haco__s0" in printed
    assert not list(out.glob(f"*/{FINAL_EVAL}"))  # killed before finishing; the started one has its record
    assert (out / "pe-rlhf__s0" / CELL_FILE).is_file()
    plan_text = main(["sweep", str(config), "--dry-run", "--out", str(out)]), capsys.readouterr().out
    assert "2 cells (0 finished" in plan_text[1]


@pytest.mark.parametrize("flags, message", [
    (["--deadline", "60"], "needs --backend processes"),
    (["--backend", "processes", "--deadline", "0"], "needs --backend processes and a number of seconds > 0"),
    (["--backend", "processes", "--address", "ray://head:10001"], "only with --backend ray"),
])
def test_process_backend_flags_are_checked(tmp_path, capsys, flags, message):
    from pe_rlhf.apps.cli import main

    with pytest.raises(SystemExit):
        main(["sweep", str(_tiny_sweep(tmp_path)), *flags, "--out", str(tmp_path / "out")])
    assert message in capsys.readouterr().err


def test_a_local_ray_runs_the_cells_at_normal_priority(monkeypatch):
    """Ray starts its workers at nice 15 unless told otherwise: beside any other job the cells then starve."""
    ray = pytest.importorskip("ray")
    from pe_rlhf.apps.sweeps.execution import RAY_WORKER_NICENESS, _init_ray

    if ray.is_initialized():
        ray.shutdown()
    monkeypatch.delenv(RAY_WORKER_NICENESS, raising=False)
    _, started = _init_ray(None)
    try:
        assert started

        @ray.remote(num_cpus=0)
        def niceness():
            import os

            return os.nice(0)

        assert ray.get(niceness.remote()) <= os.nice(0)  # not below the sweep's own priority (Ray: +15)
    finally:
        ray.shutdown()


def test_a_baseline_without_a_warm_up_reads_as_zero_warm_up_steps(tmp_path):
    """HG-DAgger's config has no collector.warmup_steps: the sweep's curves must not fail on it (table1_rlhf)."""
    from pe_rlhf.apps.sweeps.plots import run_warmup_steps

    (tmp_path / "hg").mkdir()
    (tmp_path / "hg" / "config.yaml").write_text("collector:\n  total_frames: 100\n")
    (tmp_path / "pe").mkdir()
    (tmp_path / "pe" / "config.yaml").write_text("collector:\n  warmup_steps: 2500\n")
    assert run_warmup_steps(tmp_path / "hg") == 0.0 and run_warmup_steps(tmp_path / "pe") == 2500.0
    assert run_warmup_steps(tmp_path / "none") == 0.0
