"""Issue 43 retired ``logger.csv/wandb/tensorboard/mlflow``, ``logger.wandb_mode``, ``logger.wandb_project``,
``logger.out_dir``, ``mentor.seed`` and ``actor_selection.split``: a run folder saved before still loads (``--resume``,
a trained policy, a value source), translated to the settings that replaced them; a command line that names one is
refused in one line saying what took its place."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pe_rlhf.algorithms.baselines.config import load_baseline_config
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.runtime.config import save_config, to_container
from pe_rlhf.runtime.config_rules import ConfigError

ROOT = Path(__file__).resolve().parents[2]
SAVED_BEFORE = ROOT / "docs" / "results" / "claims" / "warmup" / "expert_sac_rs_seed0" / "config.yaml"


def as_saved_before_issue_43(values: dict, **logger_switches: bool) -> dict:
    """A run's saved config as the recipes wrote it before issue 43 (its retired settings at their defaults)."""
    logger = values["logger"]
    switches = {"csv": True, "wandb": False, "tensorboard": False, "mlflow": False, **logger_switches}
    values["logger"] = {"out_dir": None, **switches, "wandb_mode": "offline", "wandb_project": logger["project"],
                        "log_every": logger["log_every"]}
    values["mentor"]["seed"] = values["seed"]
    values["actor_selection"]["split"] = "train"
    return values


def write_old(path: Path, values: dict) -> Path:
    path.write_text(yaml.safe_dump({"algorithm": "pe-rlhf", **values}, sort_keys=False))
    return path


def test_an_old_pe_rlhf_run_config_loads_as_the_new_settings(tmp_path):
    now = load_config(overrides=["profile=smoke", "seed=3", "logger.backends=[csv,wandb]", "logger.project=mine"])
    old = as_saved_before_issue_43(to_container(now), wandb=True)
    assert old["logger"]["wandb_project"] == "mine" and old["mentor"]["seed"] == 3
    loaded = load_config(write_old(tmp_path / "config.yaml", old), apply_profile=False)
    assert to_container(loaded) == to_container(now)
    assert list(loaded.logger.backends) == ["csv", "wandb"] and loaded.logger.project == "mine"


def test_the_saved_config_of_an_older_baseline_run_loads():
    """A real run folder from before the change (kept in the docs as the warm-up claim's expert)."""
    assert "wandb_mode: offline" in SAVED_BEFORE.read_text()
    cfg = load_baseline_config("sac_rs", SAVED_BEFORE, apply_profile=False)
    assert to_container(cfg)["logger"] == {"backends": ["csv"], "project": "pe-rlhf", "log_every": 1}
    assert cfg.seed == 0 and cfg.collector.total_frames == 30_000


def test_metrics_csv_stays_on_for_an_old_run_that_turned_it_off(tmp_path):
    old = as_saved_before_issue_43(to_container(load_config(overrides=["profile=smoke"])), csv=False,
                                   tensorboard=True)
    loaded = load_config(write_old(tmp_path / "config.yaml", old), apply_profile=False)
    assert list(loaded.logger.backends) == ["csv", "tensorboard"]


def test_a_run_folder_saved_by_logger_out_dir_is_its_own(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs" / "x").mkdir(parents=True)
    old = as_saved_before_issue_43(to_container(load_config(overrides=["profile=smoke"])))
    old["logger"]["out_dir"] = "runs/x"
    loaded = load_config(write_old(tmp_path / "runs" / "x" / "config.yaml", old), apply_profile=False)
    assert "out_dir" not in loaded.logger
    with pytest.raises(ConfigError, match=r"^logger\.out_dir='runs/x' is invalid: no longer a setting .*--out DIR"):
        load_config(write_old(tmp_path / "elsewhere.yaml", old), apply_profile=False)


def test_an_old_mentor_seed_other_than_the_seed_is_dropped_with_a_warning(tmp_path):
    old = as_saved_before_issue_43(to_container(load_config(overrides=["profile=smoke", "seed=2"])))
    old["mentor"]["seed"] = 0  # a run started with seed=2 alone
    with pytest.warns(UserWarning, match=r"mentor\.seed=0 is no longer a setting: the mentor is seeded from seed=2"):
        loaded = load_config(write_old(tmp_path / "config.yaml", old), apply_profile=False)
    assert "seed" not in loaded.mentor and loaded.seed == 2


def test_a_saved_actor_selection_split_other_than_train_is_refused(tmp_path):
    old = as_saved_before_issue_43(to_container(load_config(overrides=["profile=smoke"])))
    old["actor_selection"]["split"] = "test"
    with pytest.raises(ConfigError) as refused:
        load_config(write_old(tmp_path / "config.yaml", old), apply_profile=False)
    assert "\n" not in str(refused.value) and str(refused.value).startswith("actor_selection.split='test' is invalid")


@pytest.mark.parametrize(("override", "says"), [
    ("mentor.seed=3", "the mentor is seeded from the run's seed"),
    ("logger.wandb=true", "logger.backends lists the loggers"),
    ("logger.wandb_mode=online", "WANDB_MODE"),
    ("logger.wandb_project=x", "logger.project"),
    ("logger.out_dir=runs/x", "--out DIR"),
    ("actor_selection.split=train", "train scenes only"),
])
def test_a_retired_override_is_refused_in_one_line_saying_what_replaced_it(override, says):
    key, value = override.split("=")
    loads = [load_config] + ([] if key.startswith("actor_selection") else  # a baseline has no actor_selection
                             [lambda overrides: load_baseline_config("iwr", overrides=overrides)])
    for load in loads:
        with pytest.raises(ConfigError) as refused:
            load(overrides=[override])
        message = str(refused.value)
        assert message.startswith(f"{key}={value} is invalid: no longer a setting: ") and says in message
        assert "\n" not in message and refused.value.field == key


def test_a_new_run_saves_no_retired_setting(tmp_path):
    path = save_config(load_config(overrides=["profile=smoke"]), tmp_path / "config.yaml", "pe-rlhf")
    saved = yaml.safe_load(path.read_text())
    assert saved["logger"] == {"backends": ["csv"], "project": "pe-rlhf", "log_every": 1}
    assert "seed" not in saved["mentor"] and "split" not in saved["actor_selection"]
