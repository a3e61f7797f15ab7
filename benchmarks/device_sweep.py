"""A sweep's cells on a machine where Ray is not installed (the lent GPU machine), then a tar.gz of what came out:
``pe-rlhf sweep --backend processes --deadline`` (:mod:`pe_rlhf.apps.sweeps.processes`: a process per cell, at
most ``--parallel`` at once, stopped after ``--deadline`` seconds) and ``--pack`` (every cell folder without its
checkpoints and GIF, the logs, ``device.json``).

The packed folders drop into the sweep's ``--out`` on another machine, where ``pe-rlhf sweep`` counts the
finished ones. ``optim.device`` stays the recipe's ``auto``: on a GPU machine the learner's updates run on CUDA.
A cell still running at the deadline is stopped and packed without ``final_eval.json`` (its ``metrics.csv``
shows how far it got).

    python benchmarks/device_sweep.py recipes/sweeps/loss_ablations.yaml --out runs/sweeps/loss_ablations \\
        --only '__s[01]$' --parallel 12 --deadline 500 --pack "$OUT/cells.tar.gz"
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import tarfile
import time
from pathlib import Path

SKIPPED_IN_PACK = ("checkpoints", ".gif")


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
    from pe_rlhf.apps.sweeps.processes import run_cells_in_processes
    from pe_rlhf.apps.sweeps.spec import load_sweep

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config")
    parser.add_argument("--out", required=True)
    parser.add_argument("--only", action="append", default=None, metavar="REGEX")
    parser.add_argument("--parallel", type=int, default=os.cpu_count())
    parser.add_argument("--deadline", type=float, default=None, help="seconds; running cells are stopped")
    parser.add_argument("--pack", default=None, help="a tar.gz of the results")
    args = parser.parse_args(argv)

    spec = load_sweep(args.config)
    cells = [c for c in expand(spec) if not args.only or any(re.search(p, c.name) for p in args.only)]
    out = Path(args.out)
    started = time.time()
    report = run_cells_in_processes(cells, out, max_parallel=args.parallel, num_cpus=spec.num_cpus,
                                    progress=False, name=spec.name, deadline=args.deadline)
    states = {**{n: "done" for n in report.finished}, **{n: f"failed ({e})" for n, e in report.failed.items()},
              **{n: "stopped at the deadline" for n in report.stopped}}
    if args.pack:
        pack(out, Path(args.pack), {**device_facts(), "seconds": time.time() - started, "cells": states})
    return 0 if all(v == "done" for v in states.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
