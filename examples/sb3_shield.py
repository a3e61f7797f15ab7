"""Deploy a Stable-Baselines3 driving policy under the runtime safety shield (Simplex).

A tiny SAC agent is trained for a few hundred steps on the driving env (far too few to drive well: that is the
point, a policy you would not trust alone), then driven on train scenes alone and inside
:class:`~pe_rlhf.wrappers.SafetyShieldWrapper`. Each step the shield forecasts the agent's action and IDM-MOBIL's
(seconds until a crash or leaving the road) and executes IDM-MOBIL's where the agent's fails more than 0.5 s
sooner, until it no longer does; ``info`` says when (``shield_override``) and why (``policy_time_to_failure``,
``physics_time_to_failure``). Any model with ``predict(obs)`` deploys the same way.

Run ``python examples/sb3_shield.py`` (about a minute on one core): it prints success and violation (a crash or
leaving the road) alone and shielded, and the share of steps the shield drove.
"""

import numpy as np
import torch
from stable_baselines3 import SAC

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.wrappers import SafetyShieldWrapper

CONFIG = DrivingConfig(split="train", lane_features=True)


def train(total_steps: int = 300, seed: int = 0) -> SAC:
    """A SAC agent after ``total_steps`` steps on train scenes (a small network, CPU)."""
    model = SAC("MlpPolicy", make_gym_env(CONFIG), learning_starts=100, buffer_size=total_steps, batch_size=64,
                policy_kwargs={"net_arch": [64, 64]}, seed=seed, device="cpu", verbose=0)
    return model.learn(total_timesteps=total_steps)


def drive(model, scenes, shielded: bool) -> dict:
    """``model`` on each scene (``predict``, deterministic), shielded or alone: success, violation and the
    share of steps the shield overrode."""
    env = make_gym_env(CONFIG)
    env = SafetyShieldWrapper(env) if shielded else env
    success = violation = overrides = steps = 0
    for scene in scenes:
        obs, _ = env.reset(options={"scene_seed": scene})
        while True:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            steps += 1
            overrides += bool(info.get("shield_override", False))
            if terminated or truncated:
                break
        success += bool(info["success"])
        violation += bool(info["crash_vehicle"] or info["crash_object"] or info["out_of_road"])
    n = len(scenes)
    return {"success": success / n, "violation": violation / n, "override_share": overrides / steps}


if __name__ == "__main__":
    torch.set_num_threads(1)
    model = train()
    scenes = list(range(5))
    for shielded in (False, True):
        result = drive(model, scenes, shielded)
        print(f"{'shielded' if shielded else 'alone':>8}: " + ", ".join(f"{k} {v:.2f}" for k, v in result.items()))
