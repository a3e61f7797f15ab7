"""Frame-time jitter of human-paced training: updates in a learner thread vs inline, same run.

Runs the recipe's training loop (``recipes/pe_rlhf/train.py``'s ``train``: collector, replay buffer,
PERLHFLoss updates, logging) as a person would drive it, ``collector.realtime_hz`` = 10 with
:class:`~pe_rlhf.transforms.RealtimePacing`, but with the simulated ``professional`` mentor in
the person's place (no window is drawn). Each mode collects a short warm-up (``--warmup`` frames;
the Q-ensemble fit at its end stalls once and is left out) and then ``--seconds * hz`` online
frames (rounded up to whole batches) with ``optim.updates_per_batch`` updates per 100 frames:

- ``async`` (``optim.async_updates=true``): the updates run in a thread beside acting;
- ``sync`` (``false``, the loop for simulated mentors): they run between batches, acting waits.

Reported per mode over the online frames: frame time, jitter ``|frame_time - 1/hz|``
(p50/p95/p99/max, ms), late frames (tick > 10% of a period after its deadline), and the learner's
pace (``train/update_backlog``: updates owed by earlier batches and not yet run when a batch arrives;
async runs what is still owed after collection, so both modes end with the same number of updates).

    python benchmarks/realtime_jitter.py [--seconds 60] [--hz 10] [--profile cpu] [--modes async,sync]
        [--json docs/results/realtime_jitter.json]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import tempfile
import time
import warnings
from pathlib import Path

import torch

from pe_rlhf.runtime.config import to_container
from pe_rlhf.runtime.metrics_logger import MetricsLogger
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.recipe import load_recipe_script
from pe_rlhf.transforms import RealtimePacing

MODES = {"async": "true", "sync": "false"}
train = load_recipe_script("pe_rlhf", Path(__file__).resolve().parents[1] / "recipes").train  # the recipe's loop


def run_mode(mode: str, args) -> dict:
    """One training run in ``mode``; the paced env is captured to read its frame times afterwards."""
    per_batch = int(load_config(overrides=[f"profile={args.profile}"]).collector.frames_per_batch)
    online = math.ceil(args.seconds * args.hz / per_batch) * per_batch  # whole batches
    cfg = load_config(overrides=[
        f"profile={args.profile}", "mentor.name=professional", f"collector.realtime_hz={args.hz}",
        f"optim.async_updates={MODES[mode]}", f"collector.total_frames={args.warmup + online}",
        f"collector.warmup_steps={args.warmup}", "eval.every_frames=0", "eval.episodes=1",
        "checkpoint.every_frames=0", f"seed={args.seed}"])
    envs = []
    build_train_env = builders.build_train_env

    def capture(*a, **k):
        envs.append(build_train_env(*a, **k))
        return envs[-1]

    builders.build_train_env = capture
    try:
        with tempfile.TemporaryDirectory() as out:
            started = time.perf_counter()
            with MetricsLogger(out, config=to_container(cfg)) as logger:
                final = train(cfg, Path(out), logger)
            wall = time.perf_counter() - started
            with open(Path(out) / "metrics.csv") as f:
                rows = list(csv.DictReader(f))
    finally:
        builders.build_train_env = build_train_env
    pacing = builders.find_transform(envs[0], RealtimePacing)
    # the first online frame holds the warm-up's ensemble fit (a one-off stall in both modes): left out
    stats = pacing.frame_stats(last=online - 1)
    backlogs = [int(float(r["train/update_backlog"])) for r in rows]  # owed when each batch arrived
    result = {"mode": mode, "wall_s": wall, "online_frames": online, **stats,
              "updates_done": int(final["training"]["updates"]),  # all owed: async runs the rest after collection
              "update_backlog_max": max(backlogs), "update_backlog_last": backlogs[-1],
              "update_seconds": float(final["training"]["update_seconds"])}
    print(f"{mode:5s}: frame {stats['frame_ms_mean']:6.1f} ms mean | jitter p50 {stats['jitter_ms_p50']:6.2f}  "
          f"p95 {stats['jitter_ms_p95']:7.2f}  p99 {stats['jitter_ms_p99']:7.2f}  max {stats['jitter_ms_max']:7.1f} ms"
          f" | late {int(stats['late_frames'])}/{int(stats['frames'])} | updates {result['updates_done']} "
          f"(learner behind by <= {max(backlogs)}) | wall {wall:.0f} s")
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="online collection time per mode at --hz")
    parser.add_argument("--hz", type=float, default=10.0)
    parser.add_argument("--warmup", type=int, default=100, help="warm-up frames (mentor drives; not measured)")
    parser.add_argument("--profile", default="cpu", help="recipe profile: batch, networks, updates per batch")
    parser.add_argument("--modes", default="async,sync")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(),
                        help="torch threads of the run: sync updates use them all, the async learner all but "
                             "acting's one (at least 1)")
    parser.add_argument("--json", default=None, help="write the results here")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore")  # torchrl deprecation notes, metrics logger's blank cells
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = sorted(set(modes) - set(MODES))
    if unknown:
        parser.error(f"--modes: unknown {unknown}; allowed: {sorted(MODES)}")
    torch.set_num_threads(args.threads)  # train() gives the updates this count
    results = {mode: run_mode(mode, args) for mode in modes}
    result = {"config": {k: v for k, v in vars(args).items() if k != "json"}, "torch": torch.__version__,
              "cpu_count": os.cpu_count(), "threads": torch.get_num_threads(), "results": results}
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
