"""The proxy-Q recipes' Hydra command line: ``@hydra.main`` over ``config.yaml``, profiles as a config group,
``--cfg job``, the recipe flags beside Hydra's, no change of directory and no output folder of Hydra's own."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from _scripts import assert_bad_lr_is_one_line, run_recipe, run_recipe_here
from pe_rlhf.runtime.config import to_container
from pe_rlhf.runtime.config_compose import compose_file
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.recipe import RunOptions, parse_command_line
from pe_rlhf.algorithms.proxy_q.config import finish_config, load_config
from pe_rlhf.algorithms.proxy_q.config_schema import PROXY_Q

ROOT = Path(__file__).resolve().parents[3]


METHOD_OF = {"pe_rlhf": (True, False, "proxy_value"), "haco": (False, False, "paper"),
             "haim_drl": (False, True, "paper"), "pvp": (False, False, "proxy_value")}
CFG_JOB = ["profile=smoke", "seed=3", "optim.lr=3e-4", "env.traffic_density=0.2"]


def check_cfg_job(recipe: str, code: int, printed_text: str, folder: Path) -> None:
    assert code == 0
    printed = yaml.safe_load(printed_text)
    assert printed == to_container(load_config(ROOT / "recipes" / recipe / "config.yaml", CFG_JOB))
    assert (printed["physics"]["enabled"], printed["disturbance"]["enabled"], printed["loss"]["objective"]) == \
        METHOD_OF[recipe]
    assert list(folder.iterdir()) == []  # no outputs/, .hydra/, multirun/ or log file


def test_cfg_job_prints_the_composed_config_and_leaves_the_directory_alone(tmp_path):
    proc = run_recipe("pe_rlhf", *CFG_JOB, "--cfg", "job", cwd=tmp_path)  # a fresh process, as a user runs it
    assert proc.returncode == 0, proc.stderr[-2000:]
    check_cfg_job("pe_rlhf", proc.returncode, proc.stdout, tmp_path)


@pytest.mark.parametrize("recipe", ["haco", "haim_drl", "pvp"])
def test_every_recipe_script_prints_its_own_composed_config(recipe, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, out, _ = run_recipe_here(recipe, *CFG_JOB, "--cfg", "job", monkeypatch=monkeypatch, capsys=capsys)
    check_cfg_job(recipe, code, out, tmp_path)


def test_a_bad_value_from_the_script_is_one_line_naming_field_value_and_what_is_allowed(tmp_path, monkeypatch,
                                                                                       capsys):
    assert_bad_lr_is_one_line("pe_rlhf", tmp_path, monkeypatch, capsys)


def test_the_profile_is_a_config_group_and_overrides_apply_on_top():
    cfg = load_config(overrides=["replay_buffer.batch_size=64", "profile=cpu"])  # the group, wherever it is given
    assert (cfg.profile, cfg.replay_buffer.batch_size, cfg.eval.episodes) == ("cpu", 64, 20)
    with pytest.raises(ConfigError, match=r"^profile='gpu' is invalid: allowed: \['paper', 'cpu', 'quick', 'smoke'\]"):
        load_config(overrides=["profile=gpu"])


def test_a_recipe_file_names_its_own_profile_in_its_defaults_list(tmp_path):
    (tmp_path / "config.yaml").write_text("defaults:\n  - pe_rlhf_schema\n  - _self_\n  - profile: smoke\n"
                                          "optim:\n  lr: 0.002\n")
    cfg = load_config(tmp_path / "config.yaml")
    assert (cfg.profile, cfg.collector.total_frames, cfg.optim.lr) == ("smoke", 300, 0.002)
    assert load_config(tmp_path / "config.yaml", ["profile=paper"]).collector.total_frames == 30000


def test_hydra_errors_become_one_line_config_errors():
    with pytest.raises(ConfigError, match="Ambiguous value for argument 'optim.lr=1,2'") as info:
        load_config(overrides=["optim.lr=1,2"])
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match=r"unknown config key 'optim\.lrr' \(command-line override\)"):
        compose_file(ROOT / "recipes" / "pe_rlhf" / "config.yaml", ["optim.lrr=1"], {}, recipe=True, schema=PROXY_Q)


def test_an_unknown_key_in_a_recipe_file_is_named_before_hydra_composes(tmp_path):
    (tmp_path / "config.yaml").write_text("defaults:\n  - pe_rlhf_schema\n  - _self_\n  - profile: paper\n"
                                          "optim:\n  learning_rate: 0.1\n")
    with pytest.raises(ConfigError, match=r"^unknown config key 'optim\.learning_rate' \(config file .*config\.yaml\)"):
        load_config(tmp_path / "config.yaml")


def test_recipe_flags_are_taken_off_and_the_rest_is_hydras():
    options, rest = parse_command_line(["profile=smoke", "--out", "runs/x", "--cfg", "job", "seed=-1"])
    assert options == RunOptions(out="runs/x") and rest == ["profile=smoke", "--cfg", "job", "seed=-1"]
    with pytest.raises(SystemExit):
        parse_command_line(["--no-such-flag"])


def test_resume_composes_the_saved_config_over_the_schema_without_its_profile(tmp_path):
    from pe_rlhf.runtime.config import save_config
    from pe_rlhf.algorithms.proxy_q.config import algorithm_name

    cfg = load_config(overrides=["profile=smoke", "replay_buffer.batch_size=16"])
    path = save_config(cfg, tmp_path / "config.yaml", algorithm_name(cfg))
    again = load_config(path, ["collector.total_frames=400"], apply_profile=False)
    assert again.replay_buffer.batch_size == 16 and again.collector.total_frames == 400  # not the profile's 32
    assert to_container(OmegaConf.merge(to_container(cfg), {"collector": {"total_frames": 400}})) == to_container(again)


def test_after_composition_a_human_mentor_gets_its_defaults_unless_given():
    """What ``hydra_task`` does with the config ``@hydra.main`` composed: the overrides Hydra recorded say what
    was given."""
    recipe = ROOT / "recipes" / "pe_rlhf" / "config.yaml"
    composed = compose_file(recipe, ["mentor.name=human"], {}, recipe=True, schema=PROXY_Q)
    finished = finish_config(composed, ["mentor.name=human"])
    assert (finished.collector.realtime_hz, finished.optim.async_updates) == (10.0, True)
    given = ["mentor.name=human", "collector.realtime_hz=0"]
    finished = finish_config(compose_file(recipe, given, {}, recipe=True, schema=PROXY_Q), given)
    assert (finished.collector.realtime_hz, finished.optim.async_updates) == (0, True)
    with pytest.raises(ConfigError, match=r"^optim\.lr=-1 is invalid"):
        finish_config(compose_file(recipe, ["optim.lr=-1"], {}, recipe=True, schema=PROXY_Q), ["optim.lr=-1"])
