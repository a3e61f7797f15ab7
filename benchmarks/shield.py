"""The runtime shield against any driver: each policy alone and under ``SafetyShieldWrapper``, beside IDM-MOBIL.

    python benchmarks/shield.py --split test --scenes 1000-1049 --json docs/results/shield/summary.json
    python benchmarks/shield.py --split train --scenes 0-9 --agent pe-rlhf-s0=runs/pe-rlhf-s0
    python benchmarks/shield.py --split test --scenes 1000-1049 --policies --no-floor --resume \
        --from-sweep runs/sweeps/claims_learner --json docs/results/shield/summary.json   # the claims' agents

Policies: ``random`` (uniform actions), ``adversarial`` (the preset mentor driving alone), ``idm-mobil-blind``
(physics that does not see static obstacles), the persistent adversaries of :mod:`pe_rlhf.mentors.adversaries`,
and every ``--agent NAME=RUN_DIR`` (a trained run's actor, as ``pe-rlhf evaluate --checkpoint``; NAME a label,
e.g. ``pe-rlhf-professional-s0``; agents sharing a NAME prefix before ``-s<seed>`` get a mean row). With
``--from-sweep SWEEP_DIR`` the trained cells of a sweep run with ``shield`` (``pe-rlhf sweep``, e.g.
``recipes/sweeps/claims_learner.yaml``) join as ``<method>-<mentor>-s<seed>`` rows read from their
``final_eval.json`` and ``shielded_eval.json`` (the same scenes required), not evaluated again.

Writes ``{"<policy>": {"alone": {"success", "violation", ...}, "shielded": {"success", "violation",
"override_share", ...}}, "idm-mobil": {...}, "decisions_per_second": x, ...}``: rates over the scenes with 95%
bootstrap intervals (``*_ci``); ``--fallback idm-mobil`` gives the shield the paper's physics (MOBIL blind to
obstacles) in place of its own (``SHIELD_PHYSICS``: MOBIL sees them); ``decisions_per_second`` is 1 / the mean time
of a shield's decision (physics' action and the forecasts), one thread (``torch.set_num_threads(1)``). Calibrate
(``--threshold``) on ``--split train`` only.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

import pe_rlhf.mentors.registry  # noqa: F401  (registers the presets and the adversaries as policies)
from pe_rlhf.envs import DrivingConfig, scene_seeds
from pe_rlhf.envs.splits import SPLITS
from pe_rlhf.evaluation import evaluate, make_policy
from pe_rlhf.evaluation.statistics import bootstrap_interval
from pe_rlhf.mentors import ADVERSARY_NAMES
from pe_rlhf.physics import IDMMobilPolicy, PhysicsConfig
from pe_rlhf.transforms import SHIELD_PHYSICS
from pe_rlhf.wrappers import SafetyShieldWrapper

POLICIES = ("random", "adversarial", "idm-mobil-blind", *ADVERSARY_NAMES)
# The shield's fallback: its own (IDM-MOBIL with MOBIL seeing obstacles), or the paper's physics (IDM stops for
# obstacles, MOBIL does not see them), which the shield had before (the calibration notebook compares the two).
FALLBACKS = {"idm-mobil-oracle": SHIELD_PHYSICS, "idm-mobil": PhysicsConfig()}


def rates(summary: dict) -> dict:
    """Success and violation (a crash or leaving the road) rates of an evaluation summary, with 95% bootstrap
    intervals over its scenes; the shield's override share and decision latency when it drove."""
    detail = summary["episodes_detail"]
    success = [float(e["success"]) for e in detail]
    violation = [float(e["crash_vehicle"] or e["crash_object"] or e["out_of_road"]) for e in detail]
    out = {"success": float(np.mean(success)), "violation": float(np.mean(violation)),
           "success_ci": bootstrap_interval(success), "violation_ci": bootstrap_interval(violation),
           "timeout": float(np.mean([e["timeout"] for e in detail])), "episodes": len(detail)}
    if "override_share" in summary:
        out["override_share"] = summary["override_share"]
        out["decisions"] = int(sum(e["steps"] for e in detail))  # the latency: a mean over every decision
        out["decision_latency_ms"] = 1000 * sum(e["decision_latency"] * e["steps"] for e in detail) / out["decisions"]
    out["scene_seeds"] = [int(e["scene_seed"]) for e in detail]
    return out


def agent_policy(run_dir: str):
    """A trained run's actor as an evaluation policy (``pe-rlhf evaluate --checkpoint``)."""
    from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor
    from pe_rlhf.evaluation import TorchRLPolicyAdapter

    return TorchRLPolicyAdapter(load_run_actor(run_dir))


def measure(policies: dict, seeds: list[int], config: DrivingConfig, threshold: float, save=None,
            floor: bool = True, done: dict | None = None, fallback: str = "idm-mobil-oracle") -> dict:
    """Each policy (name -> factory) alone and shielded; IDM-MOBIL alone once (``floor=False``: not, measured
    apart); decisions per second. ``save(results)`` is called after each policy (a long run keeps what it
    measured); the policies of ``done`` (a saved run's, on the same scenes) are kept, not measured again."""
    kept = {name: row for name, row in (done or {}).items()
            if isinstance(row, dict) and row.get("alone", {}).get("scene_seeds") == list(seeds)
            and not name.endswith("-mean")}
    results = dict(kept)  # every saved row on these scenes stays; the means are made again
    if floor:
        results["idm-mobil"] = kept.get("idm-mobil") or {"alone": rates(evaluate(
            make_policy("idm-mobil", 0), seeds, config, progress=True, name="idm-mobil").to_dict())}
    for name, factory in policies.items():
        if name in kept:
            results[name] = kept[name]
            continue
        alone = evaluate(factory(), seeds, config, name=name).to_dict()
        shielded = evaluate(factory(), seeds, config, name=f"{name} shielded",
                            wrap_env=lambda env: SafetyShieldWrapper(
                                env, threshold, physics=IDMMobilPolicy(FALLBACKS[fallback]))).to_dict()
        results[name] = {"alone": rates(alone), "shielded": rates(shielded)}
        print(f"{name}: alone {results[name]['alone']['success']:.2f}/{results[name]['alone']['violation']:.2f}, "
              f"shielded {results[name]['shielded']['success']:.2f}/{results[name]['shielded']['violation']:.2f} "
              f"override {results[name]['shielded']['override_share']:.3f}", flush=True)
        if save is not None:
            save({**results, "decisions_per_second": decisions_per_second(results)})
    results.update(agent_means(results))
    results["decisions_per_second"] = decisions_per_second(results)
    return results


def sweep_agents(sweep_dir: Path, seeds: list[int]) -> tuple[dict, list[str]]:
    """``(rows, notes)``: the trained cells of a sweep run with ``shield`` that have both evaluations on ``seeds``,
    each ``<method>-<mentor>-s<seed>: {"alone", "shielded", "run"}`` from its ``final_eval.json`` and
    ``shielded_eval.json``; ``notes`` names the cells left out and why."""
    rows, notes = {}, []
    for cell in sorted(p for p in Path(sweep_dir).iterdir() if (p / "cell.json").is_file()):
        info = json.loads((cell / "cell.json").read_text())
        final, shielded = cell / "final_eval.json", cell / "shielded_eval.json"
        if not final.is_file() or not shielded.is_file():
            if info.get("recipe") != "evaluate":
                notes.append(f"{cell.name}: no {'final_eval.json' if not final.is_file() else 'shielded_eval.json'}")
            continue
        alone, under = rates(json.loads(final.read_text())), rates(json.loads(shielded.read_text()))
        if alone["scene_seeds"] != list(seeds) or under["scene_seeds"] != list(seeds):
            notes.append(f"{cell.name}: evaluated on other scenes")
            continue
        parts = [info["method"], None if info["mentor"] == "-" else info["mentor"], f"s{info['seed']}"]
        rows["-".join(p for p in parts if p)] = {"alone": alone, "shielded": under, "run": str(cell)}
    return rows, notes


def decisions_per_second(results: dict) -> float:
    """1 / the mean wall-clock time of a shield's decision over every shielded step of ``results``."""
    faces = [row["shielded"] for row in results.values() if isinstance(row, dict) and "decisions" in
             row.get("shielded", {})]
    steps = sum(face["decisions"] for face in faces)
    return 1000.0 * steps / sum(face["decision_latency_ms"] * face["decisions"] for face in faces) if steps else 0.0


def decision_cpu_time(cases=(("never-brake", 2), ("seek-collision", 5), ("random", 6)), steps: int = 100) -> dict:
    """CPU seconds of one shield decision (``time.thread_time``: what one core spends, whatever else shares
    the machine), per case ``(policy, train scene)``: mean and 95th percentile over ``steps`` steps."""
    from pe_rlhf.envs import make_gym_env

    env = SafetyShieldWrapper(make_gym_env(DrivingConfig(split="train", lane_features=True)))
    out = {}
    for name, scene in cases:
        policy, (obs, _) = make_policy(name, 0), env.reset(options={"scene_seed": scene})
        cpu = []
        for _ in range(steps):
            action = policy(obs, env.unwrapped)
            start = time.thread_time()
            decision = env.core.decide(env.unwrapped, action)
            cpu.append(time.thread_time() - start)
            obs, _, terminated, truncated, _ = env.unwrapped.step(decision.action)
            if terminated or truncated:
                break
        out[f"{name}@{scene}"] = {"mean_ms": 1000 * float(np.mean(cpu)), "p95_ms": 1000 * float(np.percentile(cpu, 95))}
    return out


def agent_means(results: dict) -> dict:
    """Mean rows over the seeds of agents named ``<method>-s<seed>``: ``<method>-mean``."""
    groups: dict[str, list[str]] = {}
    for name in results:
        match = re.fullmatch(r"(.+)-s\d+", name)
        if match:
            groups.setdefault(match.group(1), []).append(name)
    out = {}
    for method, names in groups.items():
        if len(names) < 2:
            continue
        out[f"{method}-mean"] = {
            face: {key: float(np.mean([results[n][face][key] for n in names]))
                   for key in ("success", "violation", "override_share") if key in results[names[0]][face]}
            for face in ("alone", "shielded")} | {"seeds": sorted(names)}
    return out


def parse_scenes(text: str, split: str) -> list[int]:
    lo, _, hi = text.partition("-")
    first, last = int(lo), int(hi or lo)
    return [s for s in scene_seeds(split) if first <= s <= last]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=list(SPLITS), default="train")
    parser.add_argument("--scenes", default="0-9", help="a range of the split's scene seeds (test: 1000-1049)")
    parser.add_argument("--policies", nargs="*", default=list(POLICIES), help=f"default: {list(POLICIES)}")
    parser.add_argument("--agent", action="append", default=[], metavar="NAME=RUN_DIR",
                        help="a trained run's actor, alone and shielded (repeatable)")
    parser.add_argument("--from-sweep", action="append", default=[], type=Path, metavar="SWEEP_DIR",
                        help="the trained cells of a sweep run with shield, read from their evaluations (repeatable)")
    parser.add_argument("--threshold", type=float, default=0.5, help="the shield's threshold [s]")
    parser.add_argument("--fallback", choices=list(FALLBACKS), default="idm-mobil-oracle",
                        help="the shield's physics: its own (default) or the paper's IDM-MOBIL")
    parser.add_argument("--no-floor", action="store_true", help="leave out IDM-MOBIL alone (measured once, apart)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--resume", action="store_true", help="keep the policies --json already holds (same "
                        "scenes), measure the rest: a run cut short goes on where it stopped")
    parser.add_argument("--cpu-time", action="store_true", help="instead: CPU time of one decision on a few train "
                        "scenes (one core's cost, not the wall clock of a shared machine)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.cpu_time:
        cpu = decision_cpu_time()
        print(json.dumps(cpu, indent=2))
        return cpu
    seeds = parse_scenes(args.scenes, args.split)
    if not seeds:
        parser.error(f"--scenes {args.scenes}: no {args.split} scene in that range")
    if args.resume and not args.json:
        parser.error("--resume needs --json (the file to go on from)")
    done = json.loads(args.json.read_text()) if args.resume and args.json.exists() else None
    policies = {name: (lambda name=name: make_policy(name, 0)) for name in args.policies}
    for spec in args.agent:
        name, sep, run_dir = spec.partition("=")
        if not sep or not name or not Path(run_dir).is_dir():
            parser.error(f"--agent {spec!r}: NAME=RUN_DIR with an existing run folder")
        policies[name] = lambda run_dir=run_dir: agent_policy(run_dir)
    start = time.time()
    meta = {"split": args.split, "scenes": [seeds[0], seeds[-1]], "episodes": len(seeds), "threshold": args.threshold,
            "fallback": args.fallback,
            "command": "python benchmarks/shield.py " + " ".join(sys.argv[1:] if argv is None else argv)}

    def save(results: dict) -> None:
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({**results, "meta": {**meta, "seconds": round(time.time() - start)}},
                                            indent=2) + "\n")

    for sweep in args.from_sweep:
        if not sweep.is_dir():
            parser.error(f"--from-sweep {sweep}: no such sweep folder")
    results = measure(policies, seeds, DrivingConfig(split=args.split, lane_features=True), args.threshold, save,
                      floor=not args.no_floor, done=done, fallback=args.fallback)
    for sweep in args.from_sweep:
        rows, notes = sweep_agents(sweep, seeds)
        for note in notes:
            print(f"--from-sweep {sweep}: left out {note}")
        results.update(rows)
    results.update(agent_means(results))
    results["decisions_per_second"] = decisions_per_second(results)
    results["meta"] = {**meta, "seconds": round(time.time() - start)}
    save(results)
    print(f"decisions per second (one thread): {results['decisions_per_second']:.0f}; {len(seeds)} {args.split} "
          f"scenes, {results['meta']['seconds']} s")
    return results


if __name__ == "__main__":
    main()
