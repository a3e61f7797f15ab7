"""How well can a network on the agent's observation drive like the professional? BC, then DAgger.

    python benchmarks/imitation_ceiling.py --json docs/results/imitation_ceiling.json
    python benchmarks/imitation_ceiling.py --lane-features --json docs/results/imitation_ceiling_lanes.json

An upper-bound probe for every learner that imitates the mentor (HACO, PE-RLHF, HG-DAgger, BC):
the professional drives ``--initial-steps`` steps on train scenes (its actions are the labels), a
256x256 MLP is fitted by MSE (behaviour cloning), evaluated deterministically on the first
``--episodes`` test scenes; then each DAgger iteration lets the network drive ``--steps-per-iter``
steps on train scenes while the professional labels every visited state, refits on all labels so far
and evaluates again. Dense labels on the learner's own states are more than any takeover-based
method gets, so DAgger's plateau bounds what they can reach from the same observation and network.

``--lane-features`` drives the world with ``DrivingConfig(lane_features=True)``: 20 more inputs, all
within the lidar's 50 m (:mod:`pe_rlhf.envs.lane_summary`): the ego's lane slot and lane count, and
for the left, current and right lane whether it exists, the bumper gap to the first road user ahead
and behind, their speeds relative to the ego, and whether the one ahead stands (an obstacle or a
stopped car). They say nothing the lidar does not hold; they say it per lane.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from pe_rlhf.envs import DrivingConfig, make_gym_env, scene_seeds
from pe_rlhf.evaluation.evaluate import evaluate
from pe_rlhf.mentors import make_mentor

class MLPDriver:
    """The imitating network as an evaluation policy (``reset()``, ``policy(obs, env)``)."""

    def __init__(self, obs_dim: int):
        self.net = nn.Sequential(nn.Linear(obs_dim, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                                 nn.Linear(256, 2), nn.Tanh())

    def reset(self) -> None:
        pass

    def __call__(self, obs: np.ndarray, env) -> np.ndarray:
        with torch.no_grad():
            return self.net(torch.as_tensor(obs)[None])[0].numpy()


def collect(env, mentor, driver: MLPDriver, steps: int, rng, learner_drives: bool):
    """``steps`` labelled states from train scenes: (features (N, D), professional's actions (N, 2))."""
    feats, labels = [], []
    train = scene_seeds("train")
    while len(labels) < steps:
        obs, _ = env.reset(options={"scene_seed": int(rng.choice(train))})
        mentor.reset(env)
        done = False
        while not done and len(labels) < steps:
            label = np.asarray(mentor.act(env), dtype=np.float32)
            feats.append(np.asarray(obs, dtype=np.float32))
            labels.append(label)
            obs, _, term, trunc, _ = env.step(driver(obs, env) if learner_drives else label)
            done = term or trunc
    return torch.as_tensor(np.array(feats)), torch.as_tensor(np.array(labels))


def fit(driver: MLPDriver, opt, feats, labels, steps: int, batch: int = 256) -> float:
    for _ in range(steps):
        idx = torch.randint(0, len(feats), (batch,))
        loss = ((driver.net(feats[idx]) - labels[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(loss.detach())


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--initial-steps", type=int, default=20000, help="professional-driven steps for BC")
    p.add_argument("--iterations", type=int, default=3, help="DAgger iterations after BC")
    p.add_argument("--steps-per-iter", type=int, default=8000, help="learner-driven labelled steps per iteration")
    p.add_argument("--fit-steps", type=int, default=6000, help="gradient steps after each data addition")
    p.add_argument("--episodes", type=int, default=50, help="test scenes 1000.. evaluated after each fit")
    p.add_argument("--lane-features", action="store_true", help="DrivingConfig(lane_features=True): 20 more inputs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    world = {"lane_features": args.lane_features}
    env = make_gym_env(DrivingConfig(split="train", **world))
    mentor = make_mentor("professional", args.seed)
    driver = MLPDriver(env.observation_space.shape[0])
    opt = torch.optim.Adam(driver.net.parameters(), 3e-4)
    t0 = time.time()
    feats, labels = collect(env, mentor, driver, args.initial_steps, rng, learner_drives=False)
    rows = []
    for it in range(args.iterations + 1):
        loss = fit(driver, opt, feats, labels, args.fit_steps)
        summary = evaluate(driver, scene_seeds("test")[: args.episodes], DrivingConfig(split="test", **world),
                           progress=False)
        causes = collections.Counter(e.failure_cause for e in summary.episodes if not e.success)
        rows.append({"iteration": it, "method": "BC" if it == 0 else f"DAgger {it}", "labels": len(labels),
                     "fit_loss": loss, "success": summary.success_rate, "failures": dict(causes),
                     "wall_s": round(time.time() - t0, 1)})
        print(json.dumps(rows[-1]), flush=True)
        if it < args.iterations:
            f, a = collect(env, mentor, driver, args.steps_per_iter, rng, learner_drives=True)
            feats, labels = torch.cat([feats, f]), torch.cat([labels, a])
    out = {"config": vars(args) | {"json": str(args.json) if args.json else None}, "rows": rows}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
