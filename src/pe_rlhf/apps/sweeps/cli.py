"""``pe-rlhf sweep CONFIG.yaml``: run a sweep's unfinished cells as Ray tasks, then write its summary.

    pe-rlhf sweep recipes/sweeps/epsilon_sensitivity.yaml                 # local Ray, all CPUs
    pe-rlhf sweep recipes/sweeps/lower_bound.yaml --max-parallel 2 --out runs/sweeps/lb
    pe-rlhf sweep recipes/sweeps/warmup.yaml --address ray://head:10001   # a Ray cluster (shared OUT)
    pe-rlhf sweep recipes/sweeps/warmup.yaml --dry-run                    # the cells, their state, no run
    pe-rlhf sweep recipes/sweeps/lower_bound.yaml --only adversarial       # only the cells whose name matches
    pe-rlhf sweep recipes/sweeps/warmup.yaml --backend processes --deadline 540   # no Ray; stop after 9 min
"""

from __future__ import annotations

import argparse
import re
import shutil
from pathlib import Path

from pe_rlhf.apps.sweeps.cells import FINAL_EVAL, cell_dir, check_folder, is_finished
from pe_rlhf.apps.sweeps.spec import SweepConfigError, load_sweep


def _state(out: Path, cell) -> str:
    if is_finished(out, cell):
        return "finished"
    from pe_rlhf.runtime.checkpoint import find_checkpoint

    directory = cell_dir(out, cell)
    if (directory / FINAL_EVAL).is_file():
        return "shield"  # trained: the shielded evaluation is left
    return "resume" if find_checkpoint(directory / "checkpoints") is not None else "run"


def print_plan(spec, cells, out: Path) -> None:
    """The dry run: every cell, whether it is finished / resumes / runs, and its overrides."""
    states = [_state(out, c) for c in cells]
    shielding = f", {states.count('shield')} to evaluate shielded" if spec.shield is not None else ""
    print(f"sweep {spec.name}: {len(cells)} cells ({states.count('finished')} finished, "
          f"{states.count('resume')} to resume, {states.count('run')} to run{shielding}), {spec.num_cpus:g} CPU each; "
          f"out {out}" + (f"; trained cells also under the shield ({spec.shield:g} s)" if spec.shield is not None
                          else ""))
    for cell, state in zip(cells, states):
        what = cell.method.recipe + (f" --policy {cell.method.policy}" if cell.method.policy else "")
        print(f"  {state:8s} {cell.name}: {what} {' '.join(cell.overrides)}")


def select_cells(cells, patterns: list[str] | None, parser: argparse.ArgumentParser):
    """The cells whose name matches one of the ``--only`` regular expressions (all cells without any)."""
    if not patterns:
        return cells
    compiled = []
    for pattern in patterns:
        try:
            compiled.append(re.compile(pattern))
        except re.error as e:
            parser.error(f"--only {pattern!r}: not a regular expression ({e})")
    chosen = [c for c in cells if any(p.search(c.name) for p in compiled)]
    if not chosen:
        parser.error(f"--only {' '.join(patterns)}: matches none of the {len(cells)} cells "
                     f"(e.g. {', '.join(c.name for c in cells[:3])})")
    return chosen


def run_sweep_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from pe_rlhf.apps.sweeps import DEFAULT_ROOT, check_cell_configs, expand, run_cells, write_summary

    if args.max_parallel is not None and args.max_parallel < 1:
        parser.error(f"--max-parallel {args.max_parallel}: must be >= 1")
    if args.deadline is not None and (args.backend != "processes" or args.deadline <= 0):
        parser.error(f"--deadline {args.deadline}: needs --backend processes and a number of seconds > 0")
    if args.address is not None and args.backend != "ray":
        parser.error(f"--address {args.address}: a Ray cluster's address, only with --backend ray")
    try:
        spec = load_sweep(args.config)
        out = Path(args.out) if args.out else DEFAULT_ROOT / spec.name
        all_cells = expand(spec)
        cells = select_cells(all_cells, args.only, parser)
        check_cell_configs(cells)
        for cell in cells:
            check_folder(out, cell)
    except SweepConfigError as e:
        parser.error(str(e))
    if args.dry_run:
        print_plan(spec, cells, out)
        return 0
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(args.config, out / "sweep.yaml")
    common = dict(max_parallel=args.max_parallel, num_cpus=spec.num_cpus, progress=not args.no_progress,
                  name=spec.name)
    if args.backend == "processes":
        from pe_rlhf.apps.sweeps.processes import run_cells_in_processes

        report = run_cells_in_processes(cells, out, deadline=args.deadline, **common)
    else:
        try:
            report = run_cells(cells, out, address=args.address, **common)
        except RuntimeError as e:  # ray missing
            parser.error(str(e))
    paths = write_summary(out, all_cells, spec.metrics, title=spec.name, description=spec.description)
    print(f"{len(report.skipped)} cells were finished already, {len(report.finished)} finished now, "
          f"{len(report.failed)} failed" + (f", {len(report.stopped)} stopped" if report.stopped else ""))
    print(paths["summary_md"].read_text())
    for name, error in report.failed.items():
        print(f"failed: {name}: {error} (rerun the same command to retry it; log in {out / 'logs' / name}.log)")
    if report.stopped:
        print(f"stopped: {', '.join(report.stopped)} (rerun the same command to continue them)")
    return 1 if report.failed or report.stopped else 0


def add_sweep_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``pe-rlhf sweep``: a grid of recipe runs as Ray tasks, resumable, summarised."""
    p = subparsers.add_parser("sweep", help="run a grid of training runs (Ray or local processes), summarise them",
                              description="Run a sweep config's cells (method x mentor x parameter x seed) as Ray "
                              "tasks or local processes; finished cells are skipped, so rerunning continues a "
                              "sweep.")
    p.add_argument("config", metavar="CONFIG.yaml", help="sweep config (see recipes/sweeps/)")
    p.add_argument("--out", metavar="DIR", help="sweep folder (default runs/sweeps/<name>)")
    p.add_argument("--backend", choices=("ray", "processes"), default="ray", help="ray: a Ray task a cell (default); "
                   "processes: a local process a cell, no Ray needed")
    p.add_argument("--address", metavar="ADDR", help="Ray cluster address (default: a local Ray on this machine)")
    p.add_argument("--deadline", type=float, metavar="SECONDS", help="with --backend processes: stop the running "
                   "cells after this many seconds (they resume on the next run)")
    p.add_argument("--max-parallel", type=int, metavar="N", help="cells running at once (default: as many as the "
                   "CPUs hold at the config's resources.num_cpus)")
    p.add_argument("--only", action="append", metavar="REGEX", help="run only the cells whose name matches "
                   "(repeatable); the summary still covers every finished cell")
    p.add_argument("--dry-run", action="store_true", help="list the cells and their state, check configs, run nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=run_sweep_command, subparser=p)
    return p


__all__ = ["add_sweep_parser", "print_plan", "run_sweep_command"]
