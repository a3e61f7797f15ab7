"""The TorchRL env: specs, rollouts, scene selection, ParallelEnv, collectors, the physics module."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs

from pe_rlhf.envs import TEST_SEEDS, TRAIN_SEEDS
from pe_rlhf.envs.torchrl_env import BOOL_INFO, FLOAT_INFO, INT_INFO, DrivingTorchEnv, make_base_env, make_env, unwrap
from pe_rlhf.physics.module import PhysicsPolicyModule

INFO_KEYS = FLOAT_INFO + BOOL_INFO + INT_INFO


@pytest.fixture(scope="module")
def env():
    e = make_env(episode_stats=False)
    yield e
    e.close()


def test_info_key_groups_cover_the_gym_info():
    assert set(INFO_KEYS) == {
        "cost", "success", "crash_vehicle", "crash_object", "out_of_road", "route_completion",
        "travel_distance", "velocity", "overtakes", "scene_seed",
    }


def test_check_env_specs(env):
    check_env_specs(env)
    assert env.batch_size == torch.Size([])
    assert env.action_spec.shape == torch.Size([2])
    assert env.full_observation_spec["observation"].shape == torch.Size([250])
    assert isinstance(env.base_env, DrivingTorchEnv)
    assert unwrap(env) is env.base_env.driving_env
    assert unwrap(unwrap(env)) is unwrap(env)


def test_check_env_specs_with_episode_stats():
    e = make_env({"horizon": 8}, episode_stats=True)
    try:
        check_env_specs(e)
        td = e.rollout(12, break_when_any_done=False)
        assert td["next", "step_count"].dtype == torch.int64
        assert td["next", "episode_reward"].dtype == torch.float32
        steps = td["next", "step_count"].flatten().tolist()
        assert steps[:8] == list(range(1, 9))  # horizon 8 ends the first episode
        assert td["next", "truncated"].flatten().tolist()[7] or td["next", "terminated"].flatten().tolist()[7]
        rewards = td["next", "reward"].flatten()
        np.testing.assert_allclose(
            td["next", "episode_reward"].flatten()[:8].numpy(), torch.cumsum(rewards[:8], 0).numpy(), rtol=1e-5
        )
    finally:
        e.close()


def test_random_rollout_matches_the_simulator(env):
    """Step by step, the tensordict holds exactly what the gymnasium env reports."""
    torch.manual_seed(0)
    driving = unwrap(env)
    td = env.reset(TensorDict({"scene_seed": torch.tensor([1001])}, []))
    records = []
    for _ in range(50):
        td = env.rand_action(td)
        td = env.step(td)
        nxt = td["next"]
        records.append(td.clone())
        assert nxt["reward"].dtype == torch.float32 and nxt["reward"].shape == (1,)
        np.testing.assert_array_equal(nxt["observation"].numpy(), td["next", "observation"].numpy())
        info = driving._info_dict(float(nxt["cost"]))
        for k in FLOAT_INFO:
            assert nxt[k].item() == pytest.approx(info[k], rel=1e-6, abs=1e-6), k
        for k in BOOL_INFO + INT_INFO:
            assert nxt[k].item() == info[k], k
        assert nxt["velocity"].item() == pytest.approx(driving.vehicle.speed * 3.6, rel=1e-6)
        if nxt["done"].item():
            break
        td = td["next"].clone().set("action", td["action"])  # carry on from the new state
    assert len(records) >= 1


def test_rollout_shapes_and_dtypes(env):
    torch.manual_seed(1)
    td = env.rollout(50, break_when_any_done=False)
    T = td.batch_size[0]
    assert T == 50
    assert td["observation"].shape == (T, 250) and td["observation"].dtype == torch.float32
    assert td["action"].shape == (T, 2) and td["action"].dtype == torch.float32
    assert td["action"].abs().max() <= 1.0
    for k in FLOAT_INFO + ("reward",):
        assert td["next", k].shape == (T, 1) and td["next", k].dtype == torch.float32, k
    for k in BOOL_INFO + ("done", "terminated", "truncated"):
        assert td["next", k].shape == (T, 1) and td["next", k].dtype == torch.bool, k
    for k in INT_INFO:
        assert td["next", k].shape == (T, 1) and td["next", k].dtype == torch.int64, k
    assert torch.all((td["observation"] >= -1) & (td["observation"] <= 1))
    # Consistency inside the data: done = terminated | truncated; cost 1 exactly on a safety event.
    nxt = td["next"]
    assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])
    event = nxt["crash_vehicle"] | nxt["crash_object"] | nxt["out_of_road"]
    assert torch.equal(nxt["cost"] == 1.0, event)
    assert torch.all(nxt["scene_seed"] >= 0)
    assert set(nxt["scene_seed"].flatten().tolist()) <= set(TRAIN_SEEDS)
    # The last step's info is the simulator's current state.
    driving = unwrap(env)
    assert nxt["scene_seed"][-1].item() == driving.scene_seed
    assert nxt["travel_distance"][-1].item() == pytest.approx(driving.travel_distance, rel=1e-6)
    assert nxt["velocity"][-1].item() == pytest.approx(driving.vehicle.speed * 3.6, rel=1e-6)


def test_base_env_reset_loads_the_requested_scene():
    base = make_base_env()
    try:
        for seed in (1003, 7):
            td = base.reset(TensorDict({"scene_seed": torch.tensor([seed])}, []))
            assert td["scene_seed"].item() == seed
            assert unwrap(base).scene_seed == seed
            assert td["route_completion"].item() == pytest.approx(unwrap(base).progress / unwrap(base).route.length)
        td = base.reset()  # without a scene seed a training scene is drawn
        assert td["scene_seed"].item() in TRAIN_SEEDS
    finally:
        base.close()


def test_reset_loads_the_requested_scene(env):
    td = env.reset(TensorDict({"scene_seed": torch.tensor([1003])}, []))
    assert td["scene_seed"].item() == 1003
    assert unwrap(env).scene_seed == 1003


def test_set_seed_fixes_the_scene_sequence(env):
    def seeds():
        return [int(env.reset()["scene_seed"]) for _ in range(5)]

    env.set_seed(1234)
    first = seeds()
    env.set_seed(1234)
    second = seeds()
    assert first == second
    assert all(s in TRAIN_SEEDS for s in first)
    env.set_seed(99)
    assert seeds() != first  # (a 5-draw collision from 50 scenes has probability 50**-5)


def test_test_split_env_draws_test_scenes():
    e = make_env({"split": "test"})
    try:
        e.set_seed(0)
        drawn = {int(e.reset()["scene_seed"]) for _ in range(6)}
        assert drawn <= set(TEST_SEEDS)
    finally:
        e.close()


@pytest.fixture(scope="module")
def parallel_env():
    penv = ParallelEnv(2, functools.partial(make_env, {"split": "train"}))
    try:
        yield penv
    finally:
        penv.close()


def test_parallel_env(parallel_env):
    penv = parallel_env
    check_env_specs(penv)
    td = penv.rollout(20, break_when_any_done=False)
    assert td.batch_size == torch.Size([2, 20])
    assert td["observation"].shape == (2, 20, 250)
    assert td["action"].shape == (2, 20, 2)
    assert td["next", "cost"].shape == (2, 20, 1) and td["next", "cost"].dtype == torch.float32
    assert td["next", "success"].shape == (2, 20, 1) and td["next", "success"].dtype == torch.bool
    assert set(td["next", "scene_seed"].flatten().tolist()) <= set(TRAIN_SEEDS)
    # Each worker drives its own simulator: travel distances differ between the two.
    assert not torch.equal(td["next", "observation"][0], td["next", "observation"][1])


def test_parallel_env_reset_to_given_scenes(parallel_env):
    td = parallel_env.reset(TensorDict({"scene_seed": torch.tensor([[1003], [1010]])}, [2]))
    assert td["scene_seed"].flatten().tolist() == [1003, 1010]


def test_collector_batches():
    e = make_env()
    collector = Collector(e, None, frames_per_batch=50, total_frames=100)
    try:
        batches = [b for b in collector]
    finally:
        collector.shutdown()
        e.close()
    assert len(batches) == 2
    for batch in batches:
        assert batch.numel() == 50
        for k in INFO_KEYS + ("reward", "done", "observation"):
            assert ("next", k) in batch.keys(True), k
        assert batch["next", "cost"].shape[-1] == 1
        assert set(batch["next", "scene_seed"].flatten().tolist()) <= set(TRAIN_SEEDS)


def test_physics_module_drives(env):
    module = PhysicsPolicyModule(env)
    assert module.driving_env is unwrap(env)
    # Scene 0 (loaded through the base env: see test_reset_loads_the_requested_scene).
    start = env.base_env.reset(TensorDict({"scene_seed": torch.tensor([0])}, []))
    td = env.rollout(300, policy=module, auto_reset=False, tensordict=start)
    completion = td["next", "route_completion"].flatten()
    assert completion[-1] > completion[0] + 0.3
    assert torch.all(completion[1:] >= completion[:-1] - 1e-6)
    assert td["action"].dtype == torch.float32 and td["action"].shape[-1] == 2
    assert td["action"].abs().max() <= 1.0
    assert td["next", "scene_seed"].flatten().unique().tolist() == [0]
    # It drives one simulator: a batched tensordict is refused.
    batched = TensorDict({"observation": torch.zeros(2, 250)}, [2])
    with pytest.raises(ValueError, match="batch"):
        module(batched)


def test_make_env_at_package_level_is_the_torchrl_env():
    from pe_rlhf.envs import make_env as package_make_env
    from pe_rlhf.envs.torchrl_env import make_env as module_make_env

    a, b = package_make_env({"split": "train"}), module_make_env({"split": "train"})
    assert type(a) is type(b) and a.observation_spec == b.observation_spec
    td_a, td_b = a.reset(scene_seed=3), b.reset(scene_seed=3)
    assert torch.equal(td_a["observation"], td_b["observation"])
