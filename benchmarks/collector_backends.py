"""Collection env steps/s per ``collector.backend``: single vs multisync vs multiasync vs ray, same run.

Every backend collects with the recipe's PE-RLHF env (``InterventionTransform``: professional mentor,
IDM-MOBIL, a 5-member selector; ``warmup_steps=1`` so the selector runs from the second step) and a
random actor (TorchRL's ``RandomPolicy``). Worker start-up is timed separately; steps/s counts the
frames after the first batch. Backends are timed in interleaved rounds (these machines are noisy),
and each is reported as its median steps/s and as a ratio against ``single`` from the same run.

    python benchmarks/collector_backends.py [--frames 2000] [--frames-per-batch 100] [--workers 2]
        [--rounds 2] [--profile paper] [--backends single multisync multiasync ray] [--json out.json]

``ray`` runs on a local Ray instance started by the benchmark (``num_cpus`` = workers; its start-up is not timed).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from pe_rlhf.runtime.config import driving_config
from pe_rlhf.threads import torch_threads
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config


def time_backend(backend: str, workers: int, frames: int, frames_per_batch: int, profile: str) -> dict:
    """``{"startup_s", "frames", "seconds", "steps_per_s"}`` of one collection run (first batch excluded)."""
    cfg = load_config(overrides=[f"profile={profile}", f"collector.backend={backend}",
                                 f"collector.num_workers={1 if backend == 'single' else workers}",
                                 f"collector.total_frames={frames}", f"collector.frames_per_batch={frames_per_batch}",
                                 "collector.warmup_steps=1"])
    started = time.perf_counter()
    value_source = builders.build_value_source(cfg)
    env, _ = builders.build_local_env(cfg, driving_config(cfg), value_source)
    collector = builders.build_collector(cfg, env, None, value_source=value_source)  # policy None: random actions
    counted, t_first = 0, None
    try:
        for batch in collector:
            if t_first is None:
                t_first = time.perf_counter()
                startup = t_first - started
                continue
            counted += batch.numel()
        elapsed = time.perf_counter() - t_first
    finally:
        builders.shutdown_collector(collector)
    return {"startup_s": startup, "frames": counted, "seconds": elapsed, "steps_per_s": counted / elapsed}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000, help="frames per run, first batch included")
    parser.add_argument("--frames-per-batch", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--profile", default="paper", help="config profile for the env and selector")
    parser.add_argument("--backends", nargs="+", default=["single", "multisync", "multiasync", "ray"],
                        choices=["single", "multisync", "multiasync", "ray"])
    parser.add_argument("--json", default=None, help="write the results here")
    args = parser.parse_args(argv)
    if args.frames < 2 * args.frames_per_batch:
        parser.error("--frames must hold at least two batches (the first is not timed)")
    backends = list(dict.fromkeys(["single", *args.backends]))  # single: the ratios' baseline
    runs: dict[str, list[dict]] = {b: [] for b in backends}
    if "ray" in backends:
        import ray

        ray.init(address="local", num_cpus=args.workers, include_dashboard=False, log_to_driver=False)
    with torch_threads(1):  # acting runs single-threaded, as in training
        for r in range(args.rounds):
            for backend in backends:
                run = time_backend(backend, args.workers, args.frames, args.frames_per_batch, args.profile)
                runs[backend].append(run)
                print(f"round {r}: {backend:10s} {run['steps_per_s']:7.1f} steps/s "
                      f"({run['frames']} frames in {run['seconds']:.1f} s, start-up {run['startup_s']:.1f} s)")
    if "ray" in backends:
        ray.shutdown()
    single = statistics.median(run["steps_per_s"] for run in runs["single"])
    summary = {}
    for backend in backends:
        median = statistics.median(run["steps_per_s"] for run in runs[backend])
        summary[backend] = {"workers": 1 if backend == "single" else args.workers, "steps_per_s": median,
                            "ratio_vs_single": median / single,
                            "startup_s": statistics.median(run["startup_s"] for run in runs[backend])}
        print(f"{backend:10s} {median:7.1f} steps/s  x{median / single:.2f} vs single")
    result = {"args": vars(args), "summary": summary, "runs": runs}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
