"""A short PE-RLHF run's throughput on idle cores and with one core held by another process, interleaved.

    python benchmarks/run_time.py --frames 800 --warmup 200 --rounds 2 --json docs/results/run_time_contention.json

Each run is ``recipes/pe_rlhf/train.py profile=cpu`` (batch 256, one update per env step after the warm-up,
the physics-forecast selector) for ``--frames`` env steps, no evaluation, in a fresh process. Settings:

- ``shipped``: ``optim.threads=auto``: the updates take the cores other processes leave, re-checked every batch
  (:class:`pe_rlhf.threads.FreeCores`), GNU OpenMP's default waiting;
- ``fixed``: the earlier behaviour: ``optim.threads=2`` whatever the load;
- ``passive``: ``optim.threads=auto`` with ``OMP_WAIT_POLICY=PASSIVE`` (threads sleep at barriers); until
  2026-12-04 ``import pe_rlhf`` set it, so ``shipped`` rows measured before then wait so too;
- ``spin``, ``spin_30k``, ``spin_3k``: ``optim.threads=auto`` with ``GOMP_SPINCOUNT`` 300000 (GNU OpenMP's own
  default), 30000, 3000 (threads spin that many times at a barrier before they sleep);
- ``one_thread``: ``optim.threads=1``; ``async``: one update thread beside acting (``optim.async_updates=true``,
  not bit-reproducible).

Loads: ``idle`` (nothing else running) and ``busy`` (one single-threaded Python busy loop). Rounds alternate
the order. Throughput: env steps per second of the whole run (warm-up, fit, updates), from the run's own
``metrics.csv`` (``env_steps``, ``wall_time``), so a run cut at ``--timeout`` still reports its rate so far.
The figure of merit is busy/idle per setting (the issue's target: >= 0.40 for the shipped setting).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = {
    "shipped": ({}, []),
    "fixed": ({}, ["optim.threads=2"]),
    "passive": ({"OMP_WAIT_POLICY": "PASSIVE"}, []),
    "spin": ({"GOMP_SPINCOUNT": "300000"}, []),
    "spin_30k": ({"GOMP_SPINCOUNT": "30000"}, []),
    "spin_3k": ({"GOMP_SPINCOUNT": "3000"}, []),
    "one_thread": ({}, ["optim.threads=1"]),
    "async": ({}, ["optim.threads=1", "optim.async_updates=true"]),
}


def _busy_loop() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def run_once(setting: str, frames: int, warmup: int, timeout: float, seed: int = 0) -> dict:
    """One short run of ``setting`` in a fresh process; its throughput from its metrics.csv."""
    env_vars, overrides = SETTINGS[setting]
    out = Path(tempfile.mkdtemp(prefix="run_time_"))
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT",
                                                              "MKL_NUM_THREADS")}
    env.update(env_vars, SDL_VIDEODRIVER="dummy")
    command = [sys.executable, str(ROOT / "recipes" / "pe_rlhf" / "train.py"), "profile=cpu", f"seed={seed}",
               f"collector.total_frames={frames}", f"collector.warmup_steps={warmup}", "eval.every_frames=0",
               "eval.episodes=1", "checkpoint.every_frames=0", *overrides,
               "--out", str(out / "run")]
    started = time.perf_counter()
    try:
        proc = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)
        finished = proc.returncode == 0
        if not finished:
            raise RuntimeError(f"{setting}: the run failed:\n{proc.stderr[-2000:]}")
    except subprocess.TimeoutExpired:
        finished = False
    wall = time.perf_counter() - started
    rows = list(csv.DictReader(open(out / "run" / "metrics.csv"))) if (out / "run" / "metrics.csv").exists() else []
    shutil.rmtree(out, ignore_errors=True)
    rows = [r for r in rows if r.get("env_steps") and r.get("wall_time")]
    if not rows:
        return {"setting": setting, "finished": finished, "wall_s": wall, "steps": 0, "steps_per_s": 0.0}
    last = rows[-1]
    steps, seconds = float(last["env_steps"]), float(last["wall_time"])
    return {"setting": setting, "finished": finished, "wall_s": wall, "steps": steps, "train_seconds": seconds,
            "env_seconds": float(last.get("time/env_seconds") or 0),
            "update_seconds": float(last.get("time/update_seconds") or 0),
            "update_threads": float(last.get("time/update_threads") or 0), "steps_per_s": steps / seconds}


def measure(settings: list[str], frames: int, warmup: int, rounds: int, timeout: float,
            loads: tuple[str, ...] = ("idle", "busy")) -> list[dict]:
    rows = []
    for r in range(rounds):
        order = [(s, load) for s in settings for load in loads]
        for setting, load in (order if r % 2 == 0 else order[::-1]):
            hog = _busy_loop() if load == "busy" else None
            try:
                time.sleep(0.5 if hog else 0)
                row = run_once(setting, frames, warmup, timeout)
            finally:
                if hog is not None:
                    hog.kill()
                    hog.wait()
            rows.append({"round": r, "load": load, **row})
            print(f"round {r} {setting:9s} {load:4s} {row['steps_per_s']:6.2f} steps/s "
                  f"({row['steps']:.0f} steps{'' if row['finished'] else ', cut at the timeout'})", flush=True)
    return rows


def summarise(rows: list[dict], settings: list[str]) -> dict:
    out = {}
    for s in settings:
        idle = [r["steps_per_s"] for r in rows if r["setting"] == s and r["load"] == "idle"]
        busy = [r["steps_per_s"] for r in rows if r["setting"] == s and r["load"] == "busy"]
        ratios = [b / i for b, i in zip(busy, idle) if i > 0]
        out[s] = {"idle_steps_per_s": statistics.median(idle) if idle else None,
                  "busy_steps_per_s": statistics.median(busy) if busy else None,
                  "busy_over_idle": statistics.median(ratios) if ratios else None, "per_round": ratios}
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=800)
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds a run may take (its rate so far counts)")
    parser.add_argument("--settings", nargs="+", choices=sorted(SETTINGS), default=["shipped", "fixed", "passive"])
    parser.add_argument("--loads", nargs="+", choices=["idle", "busy"], default=["idle", "busy"])
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    rows = measure(args.settings, args.frames, args.warmup, args.rounds, args.timeout, tuple(args.loads))
    summary = summarise(rows, args.settings)

    def cell(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}"

    print("| setting | idle steps/s | one core busy | busy / idle |\n|---|---|---|---|")
    for s, v in summary.items():
        print(f"| {s} | {cell(v['idle_steps_per_s'])} | {cell(v['busy_steps_per_s'])} | {cell(v['busy_over_idle'])} |")
    result = {"command": " ".join(["python", "benchmarks/run_time.py", *(argv if argv is not None else sys.argv[1:])]),
              "cores": os.cpu_count(), "summary": summary, "runs": rows}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
