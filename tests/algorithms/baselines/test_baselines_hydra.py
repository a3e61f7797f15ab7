"""The baseline recipes on Hydra: ``@hydra.main`` over ``config.yaml``, each method's structured config as the one
source of defaults, its profiles as the ``profile`` config group (beside the PE-RLHF recipe's in one process),
``--cfg job``, one-line errors, no change of directory and no output folder of Hydra's own."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from _scripts import assert_bad_lr_is_one_line, run_recipe, run_recipe_here
from pe_rlhf.algorithms.baselines import METHODS, default_config, load_baseline_config
from pe_rlhf.algorithms.baselines.config import rules
from pe_rlhf.runtime.config import save_config, to_container
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.algorithms.proxy_q.config import load_config

ROOT = Path(__file__).resolve().parents[3]


CFG_JOB = ["profile=smoke", "seed=3", "optim.lr=3e-4", "env.traffic_density=0.2"]


def test_cfg_job_prints_the_composed_config_and_leaves_the_directory_alone(tmp_path):
    argv = [*CFG_JOB, "constraint.cost_limit=0.2"]
    proc = run_recipe("sac_lag", *argv, "--cfg", "job", cwd=tmp_path)  # a fresh process, as a user runs it
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert yaml.safe_load(proc.stdout) == to_container(load_baseline_config("sac_lag", overrides=argv))
    assert list(tmp_path.iterdir()) == []  # no outputs/, .hydra/, multirun/ or log file


def test_another_family_prints_its_own_composed_config(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = [*CFG_JOB, "mentor.name=amateur"]
    code, out, _ = run_recipe_here("iwr", *argv, "--cfg", "job", monkeypatch=monkeypatch, capsys=capsys)
    assert code == 0 and yaml.safe_load(out) == to_container(load_baseline_config("iwr", overrides=argv))
    assert list(tmp_path.iterdir()) == []


def test_a_bad_value_from_the_script_is_one_line_naming_field_value_and_what_is_allowed(tmp_path, monkeypatch,
                                                                                       capsys):
    assert_bad_lr_is_one_line("bc", tmp_path, monkeypatch, capsys)


@pytest.mark.parametrize("method", list(METHODS))
def test_every_field_has_a_default_and_a_rule_in_the_schema(method):
    defaults = default_config(method)
    for field in rules(method):
        OmegaConf.select(OmegaConf.create(defaults), field, throw_on_missing=True)
    assert list(defaults)[:4] == ["method", "seed", "profile", "env"] and defaults["method"] == method


def test_each_family_composes_its_own_profiles_in_one_process():
    """``profile`` is one config group; each composition registers the profiles of the schema it composes."""
    assert load_baseline_config("sac_rs", overrides=["profile=smoke"]).collector.total_frames == 300
    assert list(load_config(overrides=["profile=smoke"]).loss.hidden) == [32, 32]  # the PE-RLHF recipe's smoke
    assert load_baseline_config("bc", overrides=["profile=smoke"]).optim.updates == 100
    assert load_config(overrides=["profile=quick"]).collector.total_frames == 9000
    with pytest.raises(ConfigError, match=r"^profile='quick' is invalid: allowed: \['paper', 'cpu', 'smoke'\]"):
        load_baseline_config("ppo_rs", overrides=["profile=quick"])  # PE-RLHF's profile, not a baseline's


def test_a_recipe_file_names_its_own_profile_and_its_values_apply_before_the_overrides(tmp_path):
    (tmp_path / "config.yaml").write_text("defaults:\n  - cpo_schema\n  - _self_\n  - profile: smoke\n"
                                          "constraint:\n  cost_limit: 0.3\n")
    cfg = load_baseline_config("cpo", tmp_path / "config.yaml")
    assert (cfg.profile, cfg.collector.total_frames, cfg.constraint.cost_limit) == ("smoke", 300, 0.3)
    cfg = load_baseline_config("cpo", tmp_path / "config.yaml", ["profile=paper", "constraint.cost_limit=0.1"])
    assert (cfg.collector.total_frames, cfg.constraint.cost_limit) == (1_000_000, 0.1)
    with pytest.raises(ConfigError, match=r"^method='cpo' is invalid: this is the ppo_rs recipe's config"):
        load_baseline_config("ppo_rs", overrides=["method=cpo"])


def test_resume_composes_the_saved_config_over_the_schema_without_its_profile(tmp_path):
    cfg = load_baseline_config("sac_lag", overrides=["profile=smoke", "replay_buffer.batch_size=16"])
    path = save_config(cfg, tmp_path / "config.yaml", "sac-lag")
    again = load_baseline_config("sac_lag", path, ["collector.total_frames=400"], apply_profile=False)
    assert again.replay_buffer.batch_size == 16 and again.collector.total_frames == 400  # not the profile's 32
    assert to_container(OmegaConf.merge(to_container(cfg), {"collector": {"total_frames": 400}})) == to_container(again)
    with pytest.raises(ConfigError, match=r"^algorithm='sac-lag' is invalid"):
        load_baseline_config("sac_rs", path, apply_profile=False)
