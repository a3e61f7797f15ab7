"""Does a trained proxy-Q agent steer hard where its data drove straight, and does its critic agree?

For each checkpoint folder (``<run>/checkpoints/ckpt_<step>``, which holds the replay buffer), on
``--states`` states drawn from that buffer (fixed seed):

- ``hard_steer_share``: the share where the deterministic actor's ``|steer| > --hard`` (0.5);
- ``q_gain_on_hard`` / ``q_prefers_hard``: on those states, ``min_k Q_k(s, a_actor) - min_k Q_k(s, a_straight)``
  (``a_straight`` = the actor's action with steering 0) and the share where it is positive: whether the critic,
  not only the actor, values the hard steer;
- with ``--scenes A-B``: the actor driving alone on those TRAIN scenes (success, failures by kind, and the
  median step of the off-road failures).

    python benchmarks/steer_probe.py RUN/checkpoints/ckpt_000030000 [...] [--scenes 0-49] [--json OUT]

Written for issue 17's late collapses (docs/results/claims/README.md, "Late collapses").
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from pe_rlhf.envs.splits import parse_seeds
from pe_rlhf.evaluation import TorchRLPolicyAdapter
from pe_rlhf.evaluation.evaluate import run_episode
from pe_rlhf.envs import make_gym_env
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.runtime.checkpoint import load_checkpoint
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.model_builders import build_loss
from pe_rlhf.algorithms.proxy_q.trained_policy import run_world


def min_q(loss, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``min_k Q_k(s, a)`` of the loss's proxy-Q critics, ``(N,)``."""
    td = TensorDict({"observation": observation, "action": action}, [observation.shape[0]])
    values = []
    with torch.no_grad():
        for params in loss.qvalue_network_params.unbind(0):
            with params.to_module(loss.qvalue_network):
                values.append(loss.qvalue_network(td.clone())["state_action_value"].squeeze(-1))
    return torch.stack(values).min(0).values


def probe(checkpoint: Path, states: int, hard: float, scenes: tuple[int, ...]) -> dict:
    run = checkpoint.parent.parent
    cfg = load_config(run / "config.yaml", apply_profile=False)
    actor = builders.build_actor(cfg)
    loss, _ = build_loss(cfg, actor)
    load_checkpoint(checkpoint, modules={"loss": loss}, optimizers={}, strict=False, restore_rng_state=False)
    storage = TensorDict.load_memmap(checkpoint / "buffer_replay" / "storage")
    rows = torch.randperm(storage.shape[0], generator=torch.Generator().manual_seed(0))[:states]
    observation = storage["observation"][rows].float()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = actor(TensorDict({"observation": observation}, [len(rows)]))["action"]
    straight = action.clone()
    straight[:, 0] = 0.0
    gain = min_q(loss, observation, action) - min_q(loss, observation, straight)
    is_hard = action[:, 0].abs() > hard
    out = {"checkpoint": str(checkpoint), "states": len(rows), "hard_steer_share": float(is_hard.float().mean()),
           "q_gain_on_hard": float(gain[is_hard].mean()) if is_hard.any() else None,
           "q_prefers_hard": float((gain[is_hard] > 0).float().mean()) if is_hard.any() else None}
    if scenes:
        env = make_gym_env(run_world(run))
        policy = TorchRLPolicyAdapter(actor)
        episodes = [run_episode(env, policy, seed) for seed in scenes]
        env.close()
        off_road = [e.steps for e in episodes if e.out_of_road]
        out["alone"] = {"scenes": f"{scenes[0]}-{scenes[-1]}", "success": statistics.mean(e.success for e in episodes),
                        "v/o/r/t": "/".join(str(sum(getattr(e, k) for e in episodes))
                                            for k in ("crash_vehicle", "crash_object", "out_of_road", "timeout")),
                        "off_road_median_step": statistics.median(off_road) if off_road else None}
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, help="checkpoint folders (ckpt_<step>)")
    parser.add_argument("--states", type=int, default=1000, help="buffer states to probe (default 1000)")
    parser.add_argument("--hard", type=float, default=0.5, help="|steer| counted as hard (default 0.5)")
    parser.add_argument("--scenes", default="", help="train scenes 'A-B' to drive the actor alone on")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    scenes = parse_seeds(args.scenes) if args.scenes else ()
    if any(s >= 1000 for s in scenes):
        parser.error("--scenes: train scenes only (0-49); the test scenes are for final evaluations")
    results = []
    for checkpoint in args.checkpoints:
        if not (checkpoint / "buffer_replay").is_dir():
            parser.error(f"{checkpoint}: not a checkpoint folder with a replay buffer")
        results.append(probe(checkpoint, args.states, args.hard, scenes))
        print(json.dumps(results[-1]))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return results


if __name__ == "__main__":
    main()
