"""Issue 17: the actor picked on TRAIN scenes against the last one, each on all 50 test scenes.

For every finished cell of a sweep that kept a checkpoint every K frames (``recipes/sweeps/claims_select.yaml``),
each checkpoint's actor is scored on the first ``--episodes`` train scenes and the best is picked by the rule a
run applies with ``actor_selection.every_frames=K`` (:class:`pe_rlhf.runtime.actor_selection.ActorSelection`:
success, then route completion, then the later one); then the picked actor and the last are evaluated on the
test scenes. The test scenes choose nothing. The train-scene success the run logged at a checkpoint's step
(its periodic evaluation on those scenes, ``eval.split=train``) is taken as that checkpoint's, and only the
checkpoints tied at the best success are evaluated again for their route completion (``--rescore``: every
checkpoint, which also checks that the logged success is what an evaluation now gives: it is deterministic).

    python benchmarks/select_checkpoint.py runs/sweeps/claims_select [--episodes 20] [--test-episodes 50]

Writes, in the sweep folder: ``cells_picked.csv`` and ``cells_last.csv`` (``cells.csv``'s columns with the test
metrics of the picked and of the last actor, for ``benchmarks/claims_summary.py``) and ``select_checkpoint.json``
(per cell: the train scores, the picked step, both test summaries, and the train-scene success the run logged at
each step). Each cell's result
is cached in its folder (``select_checkpoint.json``), so a rerun does only the cells not yet done. Prints a
table, with the mean and 95% bootstrap interval of each over the cells per method.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
from pathlib import Path

from tqdm import tqdm

from pe_rlhf.algorithms.proxy_q.trained_policy import load_actor, run_world
from pe_rlhf.envs import scene_seeds
from pe_rlhf.evaluation import TorchRLPolicyAdapter, evaluate
from pe_rlhf.evaluation.statistics import bootstrap_interval
from pe_rlhf.runtime.actor_selection import ActorSelection
from pe_rlhf.runtime.checkpoint import list_checkpoints
from pe_rlhf.threads import torch_threads

TEST_METRICS = ("success_rate", "safety_violation", "episodic_return", "route_completion", "travel_distance",
                "travel_velocity", "overtake_count")
CACHE = "select_checkpoint.json"


def _evaluate(actor, world, split: str, episodes: int) -> dict:
    seeds = scene_seeds(split)[:episodes]
    summary = evaluate(TorchRLPolicyAdapter(actor), seeds, dataclasses.replace(world, split=split),
                       progress=False).to_dict()
    return {k: v for k, v in summary.items() if k not in ("episodes_detail", "env_config")}


def _logged_train_success(cell: Path) -> dict[int, float]:
    """``eval/success_rate_mean`` as the run logged it, by step (its periodic evaluation on train scenes)."""
    with open(cell / "metrics.csv", newline="") as f:
        return {int(float(r["step"])): float(r["eval/success_rate_mean"]) for r in csv.DictReader(f)
                if r.get("eval/success_rate_mean") not in (None, "")}


def select_cell(cell: Path, episodes: int, test_episodes: int, rescore: bool = False) -> dict:
    """Score every checkpoint of ``cell`` on train scenes, pick, and evaluate the picked and the last on test."""
    cached = cell / CACHE
    if cached.is_file() and not rescore:
        result = json.loads(cached.read_text())
        if result["episodes"] == episodes and result["test_episodes"] == test_episodes:
            return result
    world = run_world(cell)
    checkpoints = list_checkpoints(cell / "checkpoints")
    if not checkpoints:
        raise FileNotFoundError(f"{cell}: no checkpoints")
    logged = _logged_train_success(cell)
    if not rescore and any(int(c.name.split("_")[1]) not in logged for c in checkpoints):
        raise ValueError(f"{cell}: metrics.csv has no train-scene evaluation at every checkpoint's step "
                         "(run with eval.split=train and eval.every_frames=checkpoint.every_frames, or --rescore)")
    with torch_threads(1):
        actors = [(int(c.name.split("_")[1]), load_actor(cell, checkpoint=c)) for c in checkpoints]
        best = max(logged[step] for step, _ in actors) if not rescore else None
        picking = ActorSelection(actors[-1][1], every=0, episodes=episodes)
        measured = {}
        for step, actor in actors:
            if rescore or logged[step] == best:
                summary = _evaluate(actor, world, "train", episodes)
                measured[str(step)] = summary["success_rate"]["mean"]
            else:  # below the best on success: its route completion cannot matter
                summary = {"success_rate": {"mean": logged[step]}, "route_completion": {"mean": float("nan")}}
            picking.consider(actor, step, summary)
        last_step, last = actors[-1]
        result = {"cell": cell.name, "episodes": episodes, "test_episodes": test_episodes,
                  "picked_step": picking.step, "last_step": last_step, "train_scores": picking.summary()["scores"],
                  "logged_train_success": {str(k): v for k, v in logged.items()},
                  "measured_train_success": measured,
                  "picked": _evaluate(picking.actor, world, "test", test_episodes)}
        result["last"] = (result["picked"] if picking.step == last_step
                          else _evaluate(last, world, "test", test_episodes))
    cached.write_text(json.dumps(result, indent=1) + "\n")
    return result


def _cells_csv(sweep: Path, results: dict[str, dict], which: str) -> Path:
    """cells.csv with the test metrics of ``which`` (picked | last) in place of the run's final evaluation."""
    with open(sweep / "cells.csv", newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = reader.fieldnames, list(reader)
    out = sweep / f"cells_{which}.csv"
    with open(out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            if row["cell"] in results:
                summary = results[row["cell"]][which]
                row.update({k: summary[k]["mean"] for k in TEST_METRICS if k in row})
            elif row["status"] == "finished":
                row["status"] = "not selected"  # finished, but without the test evaluation: kept out of the claims
            writer.writerow(row)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="sweep folder (its cells.csv and cell folders with checkpoints)")
    parser.add_argument("--episodes", type=int, default=20, help="train scenes that score a checkpoint")
    parser.add_argument("--test-episodes", type=int, default=50, help="test scenes of the final evaluations")
    parser.add_argument("--rescore", action="store_true", help="evaluate every checkpoint on the train scenes again")
    args = parser.parse_args(argv)
    if not (args.sweep / "cells.csv").is_file():
        parser.error(f"{args.sweep}: no cells.csv (not a sweep folder, or no cell has finished)")
    with open(args.sweep / "cells.csv", newline="") as f:
        finished = [r["cell"] for r in csv.DictReader(f) if r["status"] == "finished"]
    results = {}
    for name in tqdm(finished, desc="cells", unit="cell"):
        try:
            results[name] = select_cell(args.sweep / name, args.episodes, args.test_episodes, args.rescore)
        except (FileNotFoundError, ValueError) as err:
            parser.error(str(err))
    (args.sweep / CACHE).write_text(json.dumps(results, indent=1) + "\n")
    for which in ("picked", "last"):
        _cells_csv(args.sweep, results, which)
    print("| cell | picked step | train success at each step | test success: last / picked |")
    print("|---|---|---|---|")
    for name, r in results.items():
        scores = ", ".join(f"{int(k) // 1000}K {v['success_rate']:.2f}" for k, v in r["train_scores"].items())
        print(f"| {name} | {r['picked_step']} | {scores} | {r['last']['success_rate']['mean']:.2f} / "
              f"{r['picked']['success_rate']['mean']:.2f} |")
    methods = sorted({name.split("__")[0] for name in results})
    for method in methods:
        for which in ("last", "picked"):
            values = [r[which]["success_rate"]["mean"] for n, r in results.items() if n.split("__")[0] == method]
            lo_hi = bootstrap_interval(values)
            print(f"{method} {which}: test success {sum(values) / len(values):.2f} "
                  f"[{lo_hi[1]:.2f}, {lo_hi[2]:.2f}] over {len(values)} seeds" if lo_hi else
                  f"{method} {which}: {values}")
    return results


if __name__ == "__main__":
    sys.exit(main() and 0)
