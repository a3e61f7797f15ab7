"""Why is a trained agent's takeover data usage high? How far its actions are from the mentor's, state by state.

    python benchmarks/takeover_diagnosis.py RUN_DIR [RUN_DIR ...] [--scenes 4] [--mentor professional]
        [--json out.json]

The run's final actor drives train scenes 0..N-1 alone (deterministic actions, the run's own env config).
At every step the mentor's own action for that state is computed (the mentor does not drive), and with it
the mentor's takeover test (:class:`pe_rlhf.mentors.takeover.TakeoverRule`, the "unlikely" part: squared
Mahalanobis distance ``d2`` of the agent's action under ``N(mentor action, sigma^2)`` above
``-2 ln(1 - free_level)``) for the agent's mode and for one sampled action (what collection executes).
Prints, per run: steps, the share of steps on which the test would fire (mode / sampled), the median d2,
and the median and 90th percentile of |steering| and |throttle| differences. The mentor's danger test and
its minimum span (10 steps) are not applied, so this counts what the likelihood test alone sees.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from pe_rlhf.envs import make_gym_env
from pe_rlhf.mentors import make_mentor
from pe_rlhf.algorithms.proxy_q.trained_policy import load_actor, run_world


def _action(actor, obs, exploration) -> np.ndarray:
    with torch.no_grad(), set_exploration_type(exploration):
        td = TensorDict({"observation": torch.as_tensor(obs, dtype=torch.float32)}, [])
        return actor(td)["action"].numpy().astype(np.float64)


def diagnose(run_dir: str, scenes: int, mentor_name: str, seed: int = 0) -> dict:
    torch.manual_seed(seed)
    actor = load_actor(run_dir)
    env = make_gym_env(dataclasses.replace(run_world(run_dir), split="train"))
    mentor = make_mentor(mentor_name, seed)
    rule = mentor.rule
    d2_mode, d2_sampled, steer, throttle = [], [], [], []
    for scene in range(scenes):
        obs, _ = env.reset(options={"scene_seed": scene})
        mentor.reset(env)
        done = False
        while not done:
            mode = _action(actor, obs, ExplorationType.DETERMINISTIC)
            sampled = _action(actor, obs, ExplorationType.RANDOM)
            m = np.asarray(mentor.act(env), dtype=np.float64)
            d2_mode.append(rule.mahalanobis2(mode, m))
            d2_sampled.append(rule.mahalanobis2(sampled, m))
            steer.append(abs(mode[0] - m[0]))
            throttle.append(abs(mode[1] - m[1]))
            obs, _, terminated, truncated, _ = env.step(mode.astype(np.float32))
            done = terminated or truncated
    d2_mode, d2_sampled = np.array(d2_mode), np.array(d2_sampled)
    return {
        "run": run_dir, "scenes": scenes, "steps": len(d2_mode), "threshold_d2": rule.threshold,
        "unlikely_rate_mode": float(np.mean(d2_mode > rule.threshold)),
        "unlikely_rate_sampled": float(np.mean(d2_sampled > rule.threshold)),
        "d2_median_mode": float(np.median(d2_mode)), "d2_median_sampled": float(np.median(d2_sampled)),
        "steering_diff_p50": float(np.median(steer)), "steering_diff_p90": float(np.percentile(steer, 90)),
        "throttle_diff_p50": float(np.median(throttle)), "throttle_diff_p90": float(np.percentile(throttle, 90)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR")
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--mentor", default="professional")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    results = []
    for run in args.runs:
        r = diagnose(run, args.scenes, args.mentor)
        results.append(r)
        print(f"{run}: {r['steps']} steps; takeover test fires on {r['unlikely_rate_mode']:.2f} (mode) / "
              f"{r['unlikely_rate_sampled']:.2f} (sampled) of steps; median d2 {r['d2_median_mode']:.1f} "
              f"(threshold {r['threshold_d2']:.2f}); |steering diff| p50 {r['steering_diff_p50']:.2f} "
              f"p90 {r['steering_diff_p90']:.2f}; |throttle diff| p50 {r['throttle_diff_p50']:.2f} "
              f"p90 {r['throttle_diff_p90']:.2f}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
