"""Bad input fails at the start with the field, the value and what is allowed; checkpoints and datasets
from another env config or version are refused with the mismatch named.

(``tests/algorithms/proxy_q/test_training_config.py`` checks a rule for every config field; here are the issue's cases
end to end, through the recipe's command line.)"""

from __future__ import annotations

import json

import pytest
import torch
from _runs import train
from tensordict import TensorDict

from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.algorithms.proxy_q.config import load_config

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::FutureWarning")]

BAD = [  # override, field named, what the message must say
    ("collector.total_frames=-100", "collector.total_frames", "collector.total_frames=-100 is invalid: must be an "
                                                              "integer >= 1"),
    ("collector.warmup_steps=-5", "collector.warmup_steps", "=-5 is invalid: must be an integer >= 0"),
    ("checkpoint.every_frames=-1", "checkpoint.every_frames", "=-1 is invalid: must be an integer >= 0"),
    ("selector.epsilon_select=.nan", "selector.epsilon_select", "=nan is invalid: must be a finite number"),
    ("selector.epsilon_select=.inf", "selector.epsilon_select", "=inf is invalid: must be a finite number"),
    ("selector.epsilon_select=high", "selector.epsilon_select", "='high' is invalid: must be a finite number"),
    ("loss.gamma=1.5", "loss.gamma", "=1.5 is invalid: must be a finite number in [0, 1]"),
    ("mentor.name=expert", "mentor.name", "='expert' is invalid: allowed: ['adversarial', 'amateur'"),
    ("mentor.kwargs.skill=3", "mentor.kwargs.skill", "unknown SkillProfile field for mentor 'professional'"),
    ("env.block_types=[straight,spiral]", "env.block_types", "is invalid: unknown ['spiral']; allowed: ['straight'"),
    ("env.lidar_beams=0", "env.lidar_beams", "need lidar_beams >= 1"),
    ("env.horizon=ten", "env.horizon", "env.horizon='ten' is invalid: must be an integer"),
]


@pytest.mark.parametrize("override, field, expected", BAD, ids=[b[0] for b in BAD])
def test_invalid_config_fails_at_start_naming_field_value_and_allowed(tmp_path, override, field, expected):
    out = tmp_path / "run"
    with pytest.raises(ConfigError) as info:
        train(out, override)
    assert info.value.field == field and expected in str(info.value), str(info.value)
    assert not out.exists()  # nothing was started


def test_observation_size_follows_the_env_config():
    """Networks are built for the configured world's observation (10 + lidar beams), not a fixed 250."""
    from pe_rlhf.envs.torchrl_env import make_env
    from pe_rlhf.runtime.config import driving_config
    from pe_rlhf.algorithms.proxy_q import builders

    # the packaged value expert reads the default 270-float observation: a fitted ensemble follows any world
    cfg = load_config(overrides=["profile=smoke", "env.lidar_beams=60", "env.lane_features=false",
                                 "selector.value=warmup"])
    env = make_env(driving_config(cfg))
    assert obs_dim(cfg) == env.observation_spec["observation"].shape[-1] == 70
    td = builders.build_actor(cfg)(env.reset())
    assert td["action"].shape == (2,)
    # (members, rows): the selector's num_members (the schema's 5; the smoke profile set 2 until issue 43)
    assert builders.build_value_source(cfg).values(td["observation"].unsqueeze(0), td["action"].unsqueeze(0)).shape \
        == (int(cfg.selector.num_members), 1) == (5, 1)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A 50-frame HACO run (checkpoint at 50)."""
    from pe_rlhf.threads import torch_threads

    out = tmp_path_factory.mktemp("bad_input") / "run"
    with torch_threads(1):
        train(out, "physics.enabled=false", "collector.warmup_steps=0",
              "collector.total_frames=50", "checkpoint.every_frames=50")
    return out


def test_resuming_under_another_env_config_is_refused_naming_the_fields(finished_run):
    # refused before anything is written, naming the first changed field (issue 45: one line per setting)
    with pytest.raises(ValueError, match=r"env.horizon=60: a resume cannot change env.horizon \(the run has 50\): "
                                         r"the networks learned that world"):
        train(finished_run, "env.horizon=60", "env.traffic_density=0.8", resume=True)


def test_resuming_with_other_network_sizes_is_refused_naming_the_tensor(finished_run):
    with pytest.raises(ValueError, match=r"a resume cannot change loss.hidden \(the run has \[32, 32\]\): the "
                                         r"checkpoint's networks have the run's sizes"):
        train(finished_run, "loss.hidden=[16,16]", resume=True)


def _rewrite(ckpt, rel: str, edit) -> None:
    """Edit a checkpoint file and make its marker agree (as a newer writer would have)."""
    from pe_rlhf.runtime import checkpoint as ck

    path = ckpt / rel
    path.write_text(json.dumps(edit(json.loads(path.read_text()))))
    marker = json.loads((ckpt / "COMPLETE").read_text())
    if rel != "COMPLETE":
        marker["files"][rel] = ck._manifest_entry(path)
    (ckpt / "COMPLETE").write_text(json.dumps(marker))


def test_checkpoint_format_and_package_versions(finished_run, tmp_path):
    import shutil

    from pe_rlhf.runtime.checkpoint import CheckpointError, load_checkpoint

    run = tmp_path / "copy"
    shutil.copytree(finished_run, run)
    ckpt = run / "checkpoints" / "ckpt_000000050"
    # another pe_rlhf version, same checkpoint format: resumed, with a warning naming both versions
    _rewrite(ckpt, "state.json", lambda s: {**s, "run": {**s["run"], "pe_rlhf_version": "0.0.9"}})
    with pytest.warns(UserWarning, match=r"written by pe_rlhf 0.0.9, this is 0.1.0 \(same checkpoint format"):
        assert train(run, resume=True)["training"]["frames"] == 50
    # another checkpoint format: refused before anything is read
    _rewrite(ckpt, "COMPLETE", lambda m: {**m, "format_version": 2})
    with pytest.raises(CheckpointError, match=r"COMPLETE: checkpoint format_version 2; this pe_rlhf reads version 1"):
        load_checkpoint(ckpt, modules={}, optimizers={}, strict=False)


def _dataset(directory, config):
    from pe_rlhf.mentors.recording import DemonstrationRecorder

    t = 3
    nxt = {k: torch.zeros(t, 1, dtype=torch.bool) for k in ("done", "terminated", "truncated", "success",
                                                            "crash_vehicle", "crash_object", "out_of_road")}
    nxt.update({k: torch.zeros(t, 1) for k in ("reward", "cost", "route_completion", "travel_distance", "velocity")})
    nxt.update({k: torch.zeros(t, 1, dtype=torch.int64) for k in ("overtakes", "scene_seed")})
    with DemonstrationRecorder(directory, config, mentor_name="professional") as rec:
        rec.write_episode(TensorDict({"observation": torch.zeros(t, 250), "action": torch.zeros(t, 2),
                                      "next": {"observation": torch.zeros(t, 250), **nxt}}, batch_size=[t]))


def test_datasets_from_another_env_config_or_a_newer_version_are_refused(tmp_path):
    from pe_rlhf.envs import DrivingConfig
    from pe_rlhf.mentors.recording import load_demonstrations

    recorded = DrivingConfig(horizon=20, min_blocks=2, max_blocks=2)
    _dataset(tmp_path / "demo", recorded)
    assert len(load_demonstrations(tmp_path / "demo", recorded)) == 3
    with pytest.raises(ValueError, match="under a different DrivingConfig: horizon: recorded 20, requested 30"):
        load_demonstrations(tmp_path / "demo", DrivingConfig(horizon=30, min_blocks=2, max_blocks=2))
    meta = json.loads((tmp_path / "demo" / "metadata.json").read_text())
    (tmp_path / "demo" / "metadata.json").write_text(json.dumps({**meta, "format_version": 99}))
    with pytest.raises(ValueError, match="format_version 99 is newer than this pe_rlhf .*upgrade pe_rlhf"):
        load_demonstrations(tmp_path / "demo", recorded)
