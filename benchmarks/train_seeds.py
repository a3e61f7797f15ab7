"""PE-RLHF's full budget over several seeds: train, evaluate every final agent on the test split, aggregate.

    python benchmarks/train_seeds.py --seeds 0 1 2 --out runs/bench_30k --json docs/results/train_30k.json \
        [--episodes 50] [--compare idm-mobil] [override ...]

Each seed runs the recipe (``recipes/pe_rlhf/train.py profile=cpu seed=S`` plus the overrides) in a
subprocess into ``OUT/seed_S`` (a seed whose ``final_eval.json`` exists is not re-run, so a killed
benchmark continues), then evaluates its final actor on the first ``--episodes`` test scenes
(1000-1049 by default: the README's IDM-MOBIL row uses the same ones) and, in the same process, the
``--compare`` policy on the same scenes. The JSON holds per seed: test metrics, training safety
violations (total and per 1K steps), takeover data usage, value-takeover rate, wall time split
(env / updates / other); and the mean and std over seeds. ``OUT/takeover_rate.png`` overlays every
seed's takeover-rate curve (the claim "the takeover rate falls over training").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "pe_rlhf" / "train.py"


def run_seed(seed: int, out: Path, overrides: list[str]) -> float:
    """Train one seed (skipped when its run folder already holds a final evaluation); wall seconds."""
    if (out / "final_eval.json").exists():
        return float("nan")
    cmd = [sys.executable, str(RECIPE), "profile=cpu", f"seed={seed}", *overrides,
           "--out", str(out)]
    if (out / "checkpoints").exists():
        cmd = [sys.executable, str(RECIPE), "--resume", str(out)]
    print("$", " ".join(cmd), flush=True)
    started = time.time()
    env = dict(os.environ, SDL_VIDEODRIVER="dummy", PYTHONPATH=str(ROOT / "src"))
    with open(out.parent / f"seed_{seed}.log", "a") as log:
        subprocess.run(cmd, check=True, env=env, stdout=log, stderr=subprocess.STDOUT)
    return time.time() - started


def training_numbers(run: Path, warmup_steps: int) -> dict:
    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    _, rows = read_metrics_csv(run / "metrics.csv")
    last = rows[-1]
    steps = float(last["env_steps"])
    rates = [float(r["train/takeover_rate"]) for r in rows if r["env_steps"] > warmup_steps]
    third = max(len(rates) // 3, 1)
    return {
        "env_steps": steps,
        "safety_violations": float(last["train/safety_violations_total"]),
        "safety_violations_per_1k": 1000.0 * float(last["train/safety_violations_total"]) / steps,
        "takeover_data_usage": float(last["train/takeover_data_usage"]),
        "value_takeover_rate": float(last["train/value_takeover_rate"]),
        "takeover_rate_first_third": float(np.mean(rates[:third])) if rates else float("nan"),
        "takeover_rate_last_third": float(np.mean(rates[-third:])) if rates else float("nan"),
        "wall_s": float(last["wall_time"]),
        "env_s": float(last["time/env_seconds"]),
        "update_s": float(last["time/update_seconds"]),
    }


def plot_takeover(runs: dict[int, Path], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for seed, run in runs.items():
        _, rows = read_metrics_csv(run / "metrics.csv")
        x = np.array([r["env_steps"] for r in rows])
        y = np.array([r["train/takeover_rate"] for r in rows], dtype=float)
        k = 10  # 1K-step moving average of the per-batch rate
        smooth = np.convolve(y, np.ones(k) / k, mode="valid")
        ax.plot(x[k - 1:], smooth, label=f"seed {seed}")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("takeover rate (1K-step mean)")
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title("Takeover rate over training (warm-up: the mentor drives every step)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def recipe_method(overrides: list[str]) -> str:
    """The method the overrides make of the recipe: PE-RLHF, HACO or HAIM-DRL (for the tables' labels)."""
    sys.path.insert(0, str(ROOT / "src"))
    from pe_rlhf.algorithms.proxy_q.config import load_config, method_name

    return method_name(load_config(None, ["profile=cpu", *overrides]))


def mean_std(values: list[float]) -> dict[str, float]:
    return {"mean": float(np.mean(values)), "std": float(np.std(values))}


def markdown(result: dict) -> str:
    """The README tables: test metrics (per seed, mean +- std, the reference policy) and training figures."""
    def cell(stat):
        return f"{stat['mean']:.2f} ± {stat['std']:.2f}"

    test_keys = ("success_rate", "episodic_return", "safety_violation", "travel_distance", "travel_velocity",
                 "overtake_count")
    lines = ["| agent | success | return | safety viol. | distance m | km/h | overtakes |",
             "|---|---|---|---|---|---|---|"]
    ref = result["reference"]
    lines.append(f"| {ref['policy']} | {cell(ref['success_rate'])} | {cell(ref['episodic_return'])} | "
                 f"{cell(ref['safety_violation'])} | | | |")
    method = result.get("method", "PE-RLHF")  # results written before the field existed are PE-RLHF's
    for seed, p in result["per_seed"].items():
        lines.append(f"| {method} seed {seed} | " + " | ".join(f"{p['test'][k]['mean']:.2f}" for k in test_keys) + " |")
    o = result["over_seeds"]
    lines.append(f"| **{method}, mean ± std over seeds** | " + " | ".join(
        cell(o["test_success_rate"] if k == "success_rate" else o[f"test_{k}"]) for k in test_keys) + " |")
    lines += ["", "| seed | train safety viol. (per 1K steps) | takeover data usage | value-takeover rate | "
              "takeover rate, first → last third | wall min (env / updates) |", "|---|---|---|---|---|---|"]
    for seed, p in result["per_seed"].items():
        t = p["training"]
        lines.append(f"| {seed} | {t['safety_violations']:.0f} ({t['safety_violations_per_1k']:.2f}) | "
                     f"{t['takeover_data_usage']:.2f} | {t['value_takeover_rate']:.2f} | "
                     f"{t['takeover_rate_first_third']:.2f} → {t['takeover_rate_last_third']:.2f} | "
                     f"{t['wall_s'] / 60:.1f} ({t['env_s'] / 60:.1f} / {t['update_s'] / 60:.1f}) |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="recipe overrides added to profile=cpu")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", default="runs/bench_30k")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--compare", default="idm-mobil")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown-from", default=None, metavar="JSON",
                        help="only print (and write next to it as .md) the tables of an earlier run's JSON")
    args = parser.parse_args()
    if args.markdown_from:
        table = markdown(json.loads(Path(args.markdown_from).read_text()))
        Path(args.markdown_from).with_suffix(".md").write_text(table + "\n")
        print(table)
        return
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    sys.path.insert(0, str(ROOT / "src"))
    import torch

    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.evaluation import TorchRLPolicyAdapter, evaluate, make_policy
    from pe_rlhf.runtime.config import driving_config
    from pe_rlhf.algorithms.proxy_q.config import load_config
    from pe_rlhf.algorithms.proxy_q.trained_policy import load_actor

    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = {seed: out / f"seed_{seed}" for seed in args.seeds}
    for seed, run in runs.items():
        run.mkdir(exist_ok=True)
        run_seed(seed, run, args.overrides)
    seeds = scene_seeds("test")[: args.episodes]
    cfg = load_config(runs[args.seeds[0]] / "config.yaml", apply_profile=False)
    env_config = driving_config(cfg)
    per_seed = {}
    for seed, run in runs.items():
        summary = evaluate(TorchRLPolicyAdapter(load_actor(run)), seeds, env_config, progress=True,
                           name=f"seed {seed}").to_dict()
        per_seed[seed] = {"test": {k: summary[k] for k in ("success_rate", "episodic_return", "safety_violation",
                                                           "travel_distance", "travel_velocity", "overtake_count")},
                          "failures": summary["failure_breakdown"],
                          "training": training_numbers(run, int(cfg.collector.warmup_steps))}
    reference = evaluate(make_policy(args.compare, 0), seeds, env_config, progress=True, name=args.compare).to_dict()
    success = [p["test"]["success_rate"]["mean"] for p in per_seed.values()]
    result = {
        "command": " ".join(["python", "benchmarks/train_seeds.py", *sys.argv[1:]]),
        "method": recipe_method(args.overrides),
        "profile": str(cfg.profile),
        "total_frames": int(cfg.collector.total_frames),
        "test_scenes": [int(seeds[0]), int(seeds[-1])],
        "per_seed": per_seed,
        "over_seeds": {
            "test_success_rate": mean_std(success),
            **{k: mean_std([p["training"][k] for p in per_seed.values()])
               for k in ("safety_violations", "safety_violations_per_1k", "takeover_data_usage",
                         "value_takeover_rate", "takeover_rate_first_third", "takeover_rate_last_third",
                         "wall_s", "env_s", "update_s")},
            **{f"test_{k}": mean_std([p["test"][k]["mean"] for p in per_seed.values()])
               for k in ("episodic_return", "safety_violation", "travel_distance", "travel_velocity",
                         "overtake_count")},
        },
        "reference": {"policy": args.compare, "success_rate": reference["success_rate"],
                      "episodic_return": reference["episodic_return"],
                      "safety_violation": reference["safety_violation"]},
    }
    plot_takeover(runs, out / "takeover_rate.png")
    print(json.dumps(result["over_seeds"], indent=1))
    print(markdown(result))
    print(f"{args.compare}: success {reference['success_rate']['mean']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=float))
        Path(args.json).with_suffix(".md").write_text(markdown(result) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
