"""The per-lane summary (``DrivingConfig(lane_features=True)``): layout, values on built scenes, wiring."""

from __future__ import annotations

import numpy as np
import pytest
from _scenes import CAR_LENGTH, add_car, add_obstacle, long_road_env, place_ego

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.envs.lane_summary import LANE_FEATURES, LANE_RANGE, lane_features
from pe_rlhf.envs.observation import V_MAX, observation_size
from pe_rlhf.runtime.world import obs_dim

LEFT, OWN, RIGHT = slice(2, 8), slice(8, 14), slice(14, 20)


def test_empty_road_reads_free_lanes_and_the_ego_slot():
    env = long_road_env()
    for lane, present in ((0, (0, 1, 1)), (1, (1, 1, 1)), (2, (1, 1, 0))):
        place_ego(env, 100.0, lane=lane)
        f = lane_features(env, V_MAX)
        assert f.shape == (LANE_FEATURES,) and f.dtype == np.float32
        assert f[0] == pytest.approx(lane / 2) and f[1] == pytest.approx(3 / 4)
        for block, exists in zip((LEFT, OWN, RIGHT), present):
            expected = [1.0, 1.0, 0.0, 0.0, 1.0, 0.0] if exists else [0.0] * 6
            np.testing.assert_allclose(f[block], expected, err_msg=f"ego lane {lane}")


def test_obstacle_ahead_and_cars_beside_are_placed_in_their_lanes():
    env = long_road_env()
    place_ego(env, 100.0, lane=1, speed=10.0)
    obstacle = add_obstacle(env, 130.0, lane=1)
    add_car(env, 120.0, lane=0, speed=14.0, target_speed=14.0)  # left lane, ahead, faster
    add_car(env, 85.0, lane=2, speed=12.0, target_speed=12.0)  # right lane, behind
    add_obstacle(env, 100.0 + LANE_RANGE + 30.0, lane=2)  # beyond the lidar's range: unseen
    f = lane_features(env, V_MAX)
    own_gap = (130.0 - 100.0 - (obstacle.LENGTH + CAR_LENGTH) / 2) / LANE_RANGE
    np.testing.assert_allclose(f[OWN], [1.0, own_gap, -10.0 / V_MAX, 1.0, 1.0, 0.0], atol=1e-4)
    left_gap = (120.0 - 100.0 - CAR_LENGTH) / LANE_RANGE
    np.testing.assert_allclose(f[LEFT], [1.0, left_gap, 4.0 / V_MAX, 0.0, 1.0, 0.0], atol=1e-4)
    right_gap = (100.0 - 85.0 - CAR_LENGTH) / LANE_RANGE
    np.testing.assert_allclose(f[RIGHT], [1.0, 1.0, 0.0, 0.0, right_gap, 2.0 / V_MAX], atol=1e-4)


def test_observation_appends_the_summary_and_keeps_the_rest():
    plain = make_gym_env(DrivingConfig())
    lanes = make_gym_env(DrivingConfig(lane_features=True))
    assert lanes.observation_space.shape == (observation_size(240, True),) == (270,)
    a, _ = plain.reset(options={"scene_seed": 5})
    b, _ = lanes.reset(options={"scene_seed": 5})
    for _ in range(30):
        np.testing.assert_array_equal(a, b[:250])  # same world, same first 250 numbers
        np.testing.assert_array_equal(b[250:], lane_features(lanes.unwrapped, V_MAX))
        assert lanes.observation_space.contains(b)
        a, *_ = plain.step(np.array([0.0, 0.3], dtype=np.float32))
        b, *_ = lanes.step(np.array([0.0, 0.3], dtype=np.float32))


def test_config_field_is_validated_and_sizes_the_networks():
    from pe_rlhf.runtime.config_rules import ConfigError
    from pe_rlhf.algorithms.proxy_q import builders
    from pe_rlhf.algorithms.proxy_q.config import load_config

    with pytest.raises(ValueError, match="lane_features"):
        DrivingConfig(lane_features="yes")
    with pytest.raises(ConfigError, match="lane_features"):
        load_config(None, ["env.lane_features=maybe"])
    assert obs_dim(load_config(None, ["env.lane_features=false"])) == 250
    assert obs_dim(load_config(None, [])) == 270  # the recipes' default world has the lane summary


def test_evaluate_checkpoint_uses_the_runs_world(tmp_path):
    """`pe-rlhf evaluate --checkpoint RUN` builds the run's world: a 270-input agent needs lane_features."""
    import json

    import torch
    from omegaconf import OmegaConf

    from pe_rlhf.apps.cli import main
    from pe_rlhf.algorithms.proxy_q import builders
    from pe_rlhf.algorithms.proxy_q.config import load_config
    from pe_rlhf.algorithms.proxy_q.trained_policy import run_world

    cfg = load_config(None, ["env.lane_features=true", "env.horizon=20", "loss.hidden=[8,8]"])
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    torch.save(builders.build_actor(cfg).state_dict(), tmp_path / "actor.pt")
    assert run_world(tmp_path).lane_features and run_world(tmp_path).horizon == 20
    out = tmp_path / "eval.json"
    assert main(["evaluate", "--checkpoint", str(tmp_path), "--episodes", "1", "--no-progress",
                 "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["env_config"]["lane_features"] is True and summary["env_config"]["split"] == "test"
    assert summary["episodes"] == 1 and summary["episodes_detail"][0]["steps"] <= 20
