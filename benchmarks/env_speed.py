"""Env steps/s: raw gymnasium ``DrivingEnv`` vs the TorchRL env, same process, same seeds and actions.

Actions are recorded once by driving each scene with the IDM-MOBIL policy on the raw
env; both envs then replay exactly these actions (scenes are deterministic), so they
simulate identical trajectories and the timing isolates the env and its wrapper.
The two are timed in interleaved rounds (these machines are noisy) on one thread.

    python benchmarks/env_speed.py [--episodes 10] [--rounds 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from pe_rlhf.envs import make_gym_env, scene_seeds
from pe_rlhf.envs.torchrl_env import make_env, unwrap
from pe_rlhf.physics.policy import IDMMobilPolicy


def record_actions(seeds) -> dict[int, np.ndarray]:
    env, policy, out = make_gym_env({"split": None}), IDMMobilPolicy(), {}
    for seed in seeds:
        env.reset(options={"scene_seed": seed})
        policy.reset()
        actions, done = [], False
        while not done:
            a = policy(env)
            actions.append(a)
            _, _, term, trunc, _ = env.step(a)
            done = term or trunc
        out[seed] = np.array(actions, dtype=np.float32)
    return out


def time_raw(actions: dict[int, np.ndarray]) -> tuple[int, float]:
    env = make_gym_env({"split": None})
    steps, elapsed = 0, 0.0
    for seed, seq in actions.items():
        env.reset(options={"scene_seed": seed})
        t = time.perf_counter()
        for a in seq:
            env.step(a)
        elapsed += time.perf_counter() - t
        steps += len(seq)
    return steps, elapsed


def time_torchrl(actions: dict[int, np.ndarray]) -> tuple[int, float]:
    env = make_env({"split": None})
    driving = unwrap(env)
    steps, elapsed = 0, 0.0
    for seed, seq in actions.items():
        td = env.reset()
        driving.reset(options={"scene_seed": seed})  # same scene as the raw run
        td["observation"] = torch.as_tensor(driving_obs(driving))
        acts = torch.as_tensor(seq)
        t = time.perf_counter()
        for a in acts:
            td["action"] = a
            td = env.step(td)
            td = td["next"].exclude("reward", "done", "terminated", "truncated")
        elapsed += time.perf_counter() - t
        steps += len(seq)
    return steps, elapsed


def time_stock_highway(vehicles: int, steps: int = 600) -> float:
    """Steps/s of stock highway-v0 with a 240-beam lidar, 20 Hz sim / 10 Hz policy, random actions."""
    import gymnasium as gym
    import highway_env  # noqa: F401

    env = gym.make("highway-v0", config={
        "observation": {"type": "LidarObservation", "cells": 240, "maximum_range": 50},
        "action": {"type": "ContinuousAction"}, "simulation_frequency": 20, "policy_frequency": 10,
        "vehicles_count": vehicles, "duration": 10_000,
    })
    env.reset(seed=0)
    rng, done, n, elapsed = np.random.default_rng(0), False, 0, 0.0
    while n < steps:
        if done:
            env.reset()
        a = rng.uniform(-0.3, 0.3, 2).astype(np.float32)
        t = time.perf_counter()
        _, _, term, trunc, _ = env.step(a)
        elapsed += time.perf_counter() - t
        done, n = term or trunc, n + 1
    return n / elapsed


def driving_obs(driving) -> np.ndarray:
    from pe_rlhf.envs.observation import build_observation

    return build_observation(driving)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", default=None)
    parser.add_argument("--stock-vehicles", type=int, nargs="*", default=[10, 20],
                        help="also time stock highway-v0 with these vehicle counts (for scale)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds = scene_seeds("test")[: args.episodes]
    actions = record_actions(seeds)
    raw, trl = [], []
    for _ in range(args.rounds):
        n, t = time_raw(actions)
        raw.append(n / t)
        n, t = time_torchrl(actions)
        trl.append(n / t)
    raw_sps, trl_sps = float(np.median(raw)), float(np.median(trl))
    stock = {str(v): time_stock_highway(v) for v in args.stock_vehicles}
    result = {
        "episodes": len(seeds),
        "steps_per_round": int(sum(len(a) for a in actions.values())),
        "raw_gym_steps_per_s": raw_sps,
        "torchrl_steps_per_s": trl_sps,
        "torchrl_over_raw": trl_sps / raw_sps,
        "wrapper_overhead": raw_sps / trl_sps - 1.0,
        "rounds": args.rounds,
        "stock_highway_v0_steps_per_s_by_vehicles": stock,
        "seeds": list(seeds),
    }
    print(json.dumps(result, indent=2))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)


if __name__ == "__main__":
    main()
