"""A sweep's cells without Ray, for a machine where Ray is not installed (the lent GPU machine): a process per
cell, at most ``--parallel`` at once, until ``--deadline`` seconds have passed; then ``--pack`` a tar.gz of
what came out (every cell folder without its checkpoints and GIF, the logs, ``device.json``).

Each cell runs as under ``pe-rlhf sweep`` (:func:`pe_rlhf.apps.sweeps.execution.run_cell`: one torch thread,
its log in ``OUT/logs/``, ``final_eval.json`` when done), so the packed folders drop into the sweep's ``--out``
on another machine, where ``pe-rlhf sweep`` counts them finished. ``optim.device`` stays the recipe's
``auto``: on a GPU machine the learner's updates run on CUDA. A cell still running at the deadline is stopped
and packed without ``final_eval.json`` (its ``metrics.csv`` shows how far it got).

    python benchmarks/device_sweep.py recipes/sweeps/loss_ablations.yaml --out runs/sweeps/loss_ablations \\
        --only '__s[01]$' --parallel 12 --deadline 500 --pack "$OUT/cells.tar.gz"
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import re
import tarfile
import time
from pathlib import Path

SKIPPED_IN_PACK = ("checkpoints", ".gif")


def _run(cell, out: str) -> None:
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    from pe_rlhf.apps.sweeps.execution import run_cell

    run_cell(cell, out, threads=1)


def device_facts() -> dict:
    import torch

    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor())
    return {"torch": torch.__version__, "cuda": torch.cuda.is_available(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version()}


def pack(out: Path, path: Path, facts: dict) -> None:
    (out / "device.json").write_text(json.dumps(facts, indent=2) + "\n")
    with tarfile.open(path, "w:gz") as tar:
        tar.add(out, arcname=out.name,
                filter=lambda info: None if any(s in info.name for s in SKIPPED_IN_PACK) else info)


def main(argv: list[str] | None = None) -> int:
    from pe_rlhf.apps.sweeps import expand
    from pe_rlhf.apps.sweeps.cells import plan, write_record
    from pe_rlhf.apps.sweeps.spec import load_sweep

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config")
    parser.add_argument("--out", required=True)
    parser.add_argument("--only", action="append", default=None, metavar="REGEX")
    parser.add_argument("--parallel", type=int, default=os.cpu_count())
    parser.add_argument("--deadline", type=float, default=float("inf"), help="seconds; running cells are stopped")
    parser.add_argument("--pack", default=None, help="a tar.gz of the results")
    args = parser.parse_args(argv)

    cells = expand(load_sweep(args.config))
    if args.only:
        cells = [c for c in cells if any(re.search(p, c.name) for p in args.only)]
    out = Path(args.out)
    finished, todo = plan(out, cells)
    print(f"{len(cells)} cells: {len(finished)} finished, {len(todo)} to run, {args.parallel} at once", flush=True)
    started, running, report = time.time(), {}, {}
    context = multiprocessing.get_context("spawn")
    while (todo or running) and time.time() - started < args.deadline:
        while todo and len(running) < args.parallel:
            cell = todo.pop(0)
            write_record(out, cell)
            process = context.Process(target=_run, args=(cell, str(out.resolve())), name=cell.name)
            process.start()
            running[cell.name] = process
        for name, process in list(running.items()):
            if not process.is_alive():
                report[name] = "done" if process.exitcode == 0 else f"failed ({process.exitcode})"
                print(f"{time.time() - started:6.0f} s {name}: {report[name]}", flush=True)
                del running[name]
        time.sleep(2)
    for name, process in running.items():
        process.kill()
        report[name] = "stopped at the deadline"
        print(f"{time.time() - started:6.0f} s {name}: {report[name]}", flush=True)
    if args.pack:
        pack(out, Path(args.pack), {**device_facts(), "seconds": time.time() - started, "cells": report})
    return 0 if all(v == "done" for v in report.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
