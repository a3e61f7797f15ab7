"""The expert-policy warm-up (``collector.warmup_policy``): a trained actor from an earlier run, here a SAC
baseline run of the smoke profile, drives the warm-up instead of the mentor (spec §2 (b), Fig. 19)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from _scripts import load_pe_rlhf_recipe
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from pe_rlhf.algorithms.baselines import load_baseline_actor
from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.world import build_mentor, obs_dim
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor, run_observation_size

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore::FutureWarning"), pytest.mark.filterwarnings("ignore::UserWarning")]


def _cfg(*overrides):
    return load_config("recipes/pe_rlhf/config.yaml", ["profile=smoke", *overrides])


def test_a_baseline_run_loads_as_the_warmup_driver(sac_run):
    cfg = _cfg(f"collector.warmup_policy={sac_run}")
    driver = builders.build_warmup_driver(cfg)
    assert run_observation_size(sac_run) == obs_dim(cfg)
    actor = load_baseline_actor(sac_run)
    obs = np.random.default_rng(0).uniform(0, 1, obs_dim(cfg)).astype(np.float32)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        mode = actor(TensorDict({"observation": torch.as_tensor(obs)}, []))["action"].numpy()
    action = driver(obs, None)
    assert action.shape == (2,) and np.allclose(action, mode)  # the actor's mode, not a sample
    assert np.allclose(driver(obs, None), action)  # deterministic
    for name, p in load_run_actor(sac_run).state_dict().items():
        assert torch.equal(p, actor.state_dict()[name])
    assert builders.build_warmup_driver(_cfg()) is None  # unset: the mentor drives


def test_a_baseline_run_folder_without_the_method_record_still_loads(sac_run, tmp_path):
    """A run folder written before runs recorded ``algorithm:`` is told a baseline's by its config's ``method``."""
    import shutil

    import yaml

    config = yaml.safe_load((sac_run / "config.yaml").read_text())
    assert config["algorithm"] == "sac-rs"
    old = shutil.copytree(sac_run, tmp_path / "old")
    del config["algorithm"]
    (old / "config.yaml").write_text(yaml.safe_dump(config))
    for run in (sac_run, old):
        assert run_observation_size(run) == obs_dim(_cfg())
        for name, p in load_run_actor(run).state_dict().items():
            assert torch.equal(p, load_baseline_actor(sac_run).state_dict()[name])


def test_the_expert_drives_the_warmup_of_a_recipe_run(sac_run, tmp_path):
    recipe = load_pe_rlhf_recipe()
    # no GIF (a third of a smoke run's CPU): test_training_smoke checks the video
    final = recipe.main(["profile=smoke", "eval.video=false", f"collector.warmup_policy={sac_run}",
                         "--out", str(tmp_path)])
    assert final["training"]["frames"] == 300
    cfg = load_config(tmp_path / "config.yaml", apply_profile=False)
    assert cfg.collector.warmup_policy == str(sac_run)  # recorded with the run
    # the warm-up's transitions, as the ensemble saw them, hold the expert's actions
    env = builders.build_train_env(cfg, driving_config(cfg), build_mentor(cfg), None, None)
    transform = env.transform[-1]
    assert transform.warmup_driver is not None
    def agent(td):
        return td.set("action", torch.tensor([0.5, 0.5]))

    td = env.rollout(10, agent, tensordict=env.reset())
    expert = np.stack([transform.warmup_driver(o.numpy(), None) for o in td["observation"]])
    np.testing.assert_allclose(td["next", "behavior_action"].numpy(), expert, atol=1e-6)
    assert not td["next", "mentor_selected"].any() and td["next", "intervention"].all()


def test_bad_warmup_policy_fails_naming_the_field(sac_run, tmp_path):
    with pytest.raises(ConfigError, match="collector.warmup_policy") as e:
        builders.build_warmup_driver(_cfg(f"collector.warmup_policy={tmp_path / 'nope'}"))
    assert e.value.field == "collector.warmup_policy" and "no config.yaml" in str(e.value)
    with pytest.raises(ConfigError, match=r"reads \d+-float observations"):
        builders.build_warmup_driver(_cfg(f"collector.warmup_policy={sac_run}", "env.lane_features=false"))
    with pytest.raises(ConfigError, match="collector.warmup_policy"):
        _cfg(f"collector.warmup_policy={sac_run}", "collector.warmup_steps=0", "physics.enabled=false")
    with pytest.raises(ConfigError, match="collector.warmup_policy"):
        _cfg("collector.warmup_policy=3")
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "config.yaml").write_text((sac_run / "config.yaml").read_text())
    with pytest.raises(ConfigError, match="no actor.pt"):
        builders.build_warmup_driver(_cfg(f"collector.warmup_policy={unfinished}"))


def test_evaluate_reads_a_baseline_run_folder(sac_run, tmp_path):
    from pe_rlhf.apps.cli import main as cli

    assert cli(["evaluate", "--checkpoint", str(sac_run), "--seeds", "1000", "--no-progress",
                "--config-override", "horizon=50", "--json", str(tmp_path / "e.json")]) == 0
    summary = json.loads((tmp_path / "e.json").read_text())
    assert summary["episodes"] == 1 and summary["policy"] == f"agent:{sac_run}"
