"""Issue 17: the actor picked on TRAIN scenes against the last one, each on all 50 test scenes.

For every finished cell of a sweep that kept a checkpoint every K frames (``recipes/sweeps/claims_select.yaml``),
each checkpoint's actor is scored on the first ``--episodes`` train scenes and the best is picked by the rule a
run applies with ``actor_selection.every_frames=K actor_selection.episodes=N``
(:class:`pe_rlhf.runtime.actor_selection.ActorSelection`: success, then route completion, then the later one);
then the picked actor and the last are evaluated on the test scenes. The test scenes choose nothing.
``--holdout`` also scores every checkpoint on the train scenes the pick did not read (after the first
``--episodes``): whether a pick holds on other train scenes, judged without the test scenes.

    python benchmarks/select_checkpoint.py runs/sweeps/claims_select [--episodes 20] [--test-episodes 50] [--holdout]
        [--out FILE.json]

Every episode is cached in its cell (``select_episodes.json``: step -> scene seed -> the episode's metrics; the
evaluation is deterministic), so a rerun, or a pick on another number of scenes, evaluates only what is missing.
Writes, in the sweep folder: ``cells_picked_<N>.csv`` and ``cells_last.csv`` (``cells.csv``'s columns with the
test metrics of the picked and of the last actor, for ``benchmarks/claims_summary.py``; written once the sweep
has its ``cells.csv``) and ``select_checkpoint_<N>.json`` (per cell: the train scores, the picked step, both test
summaries). Prints a table, and the mean and 95% bootstrap interval over the cells of each method.
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
from pe_rlhf.evaluation import EpisodeResult, EvaluationSummary, TorchRLPolicyAdapter, evaluate
from pe_rlhf.evaluation.statistics import bootstrap_interval
from pe_rlhf.runtime.actor_selection import ActorSelection
from pe_rlhf.runtime.checkpoint import list_checkpoints
from pe_rlhf.threads import torch_threads

TEST_METRICS = ("success_rate", "safety_violation", "episodic_return", "route_completion", "travel_distance",
                "travel_velocity", "overtake_count")
EPISODES_CACHE = "select_episodes.json"


class CellEpisodes:
    """The evaluation episodes of one cell's checkpoints, cached in the cell (module docstring)."""

    def __init__(self, cell: Path):
        self.cell, self.path = cell, cell / EPISODES_CACHE
        self.world = run_world(cell)
        self.checkpoints = {int(c.name.split("_")[1]): c for c in list_checkpoints(cell / "checkpoints")}
        if not self.checkpoints:
            raise FileNotFoundError(f"{cell}: no checkpoints")
        self.episodes = json.loads(self.path.read_text()) if self.path.is_file() else {}
        self.actors: dict[int, object] = {}

    def actor(self, step: int):
        if step not in self.actors:
            self.actors[step] = load_actor(self.cell, checkpoint=self.checkpoints[step])
        return self.actors[step]

    def summary(self, step: int, split: str, first: int, stop: int | None) -> dict:
        """The summary of the checkpoint at ``step`` on scenes ``scene_seeds(split)[first:stop]``."""
        seeds = scene_seeds(split)[first:stop]
        done = self.episodes.setdefault(str(step), {})
        missing = [s for s in seeds if str(s) not in done]
        if missing:
            with torch_threads(1):
                found = evaluate(TorchRLPolicyAdapter(self.actor(step)), missing,
                                 dataclasses.replace(self.world, split=split), progress=False)
            done.update({str(e.scene_seed): dataclasses.asdict(e) for e in found.episodes})
            self.path.write_text(json.dumps(self.episodes) + "\n")
        summary = EvaluationSummary([EpisodeResult(**done[str(s)]) for s in seeds], self.world).to_dict()
        return {k: v for k, v in summary.items() if k not in ("episodes_detail", "env_config")}


def select_cell(cell: Path, episodes: int, test_episodes: int, holdout: bool = False) -> dict:
    """Score every checkpoint of ``cell`` on the first ``episodes`` train scenes, pick, and evaluate the picked
    and the last on the first ``test_episodes`` test scenes."""
    runs = CellEpisodes(cell)
    steps = sorted(runs.checkpoints)
    picking = ActorSelection(runs.actor(steps[-1]), every=0, episodes=episodes)
    for step in steps:
        picking.consider(runs.actor(step), step, runs.summary(step, "train", 0, episodes))
    result = {"cell": cell.name, "episodes": episodes, "picked_step": picking.step, "last_step": steps[-1],
              "train_scores": picking.summary()["scores"],
              "picked": runs.summary(picking.step, "test", 0, test_episodes),
              "last": runs.summary(steps[-1], "test", 0, test_episodes)}
    if holdout:
        others = {step: runs.summary(step, "train", episodes, None) for step in steps}
        result["holdout_train_success"] = {str(step): s["success_rate"]["mean"] for step, s in others.items()}
    return result


def _cells_csv(sweep: Path, results: dict[str, dict], which: str, out: Path) -> Path:
    """cells.csv with the test metrics of ``which`` (picked | last) in place of the run's final evaluation."""
    with open(sweep / "cells.csv", newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = reader.fieldnames, list(reader)
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
    parser.add_argument("sweep", type=Path, help="sweep folder (its cell folders with checkpoints)")
    parser.add_argument("--episodes", type=int, default=20, help="train scenes that score a checkpoint")
    parser.add_argument("--test-episodes", type=int, default=50, help="test scenes of the final evaluations")
    parser.add_argument("--holdout", action="store_true", help="also score every checkpoint on the train scenes "
                        "the pick did not read (after the first --episodes), to see whether the pick holds there")
    parser.add_argument("--only", default="", help="only the cells whose name contains this")
    args = parser.parse_args(argv)
    if not 1 <= args.episodes <= len(scene_seeds("train")):
        parser.error(f"--episodes {args.episodes}: allowed 1 to {len(scene_seeds('train'))} (the train scenes)")
    finished = sorted(p.parent.name for p in args.sweep.glob("*/final_eval.json")
                      if (p.parent / "checkpoints").is_dir() and args.only in p.parent.name)
    if not finished:
        parser.error(f"{args.sweep}: no finished cell with checkpoints (not a sweep folder, or none has finished)")
    results = {}
    for name in tqdm(finished, desc="cells", unit="cell"):
        try:
            results[name] = select_cell(args.sweep / name, args.episodes, args.test_episodes, args.holdout)
        except (FileNotFoundError, ValueError) as err:
            parser.error(str(err))
    (args.sweep / f"select_checkpoint_{args.episodes}.json").write_text(json.dumps(results, indent=1) + "\n")
    if (args.sweep / "cells.csv").is_file() and not args.only:  # the sweep writes it when its last cell is done
        _cells_csv(args.sweep, results, "picked", args.sweep / f"cells_picked_{args.episodes}.csv")
        _cells_csv(args.sweep, results, "last", args.sweep / "cells_last.csv")
    print(f"| cell | picked step | success on the first {args.episodes} train scenes at each step (on the other "
          "train scenes) | test success: last / picked |")
    print("|---|---|---|---|")
    for name, r in results.items():
        other = r.get("holdout_train_success", {})
        scores = ", ".join(f"{int(k) // 1000}K {v['success_rate']:.2f}" + (f" ({other[k]:.2f})" if k in other else "")
                           for k, v in r["train_scores"].items())
        print(f"| {name} | {r['picked_step']} | {scores} | {r['last']['success_rate']['mean']:.2f} / "
              f"{r['picked']['success_rate']['mean']:.2f} |")
    for method in sorted({name.split("__")[0] for name in results}):
        for which in ("last", "picked"):
            values = [r[which]["success_rate"]["mean"] for n, r in results.items() if n.split("__")[0] == method]
            mean, lo, hi = bootstrap_interval(values)
            print(f"{method} {which}: test success {mean:.2f} [{lo:.2f}, {hi:.2f}] over {len(values)} seeds")
    return results


if __name__ == "__main__":
    sys.exit(main() and 0)
