"""Running the cells: one Ray task per cell (local Ray by default, a cluster with ``address``), at most
``max_parallel`` at once, a tqdm bar over finished cells naming the running ones.

Each task runs the cell's recipe in the Ray worker process (:func:`run_cell`): ``OMP_NUM_THREADS`` and
torch's intra-op threads set to the cell's CPUs (1 by default), ``SDL_VIDEODRIVER=dummy``, stdout and
stderr appended to ``OUT/logs/<cell>.log``. In a sweep with ``shield`` the trained actor is then evaluated under
the runtime shield on the final evaluation's scenes (``shielded_eval.json``); a cell that had finished training
before gets that evaluation alone. A cell that raises is reported and left unfinished; the next
invocation reruns it (from its newest checkpoint when it has one). With a multi-node cluster, ``OUT``
must be a path every node sees (a shared filesystem) and pe_rlhf installed on every node. Without Ray, the
same cells run as local processes: :mod:`pe_rlhf.apps.sweeps.processes`.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from pe_rlhf.apps.sweeps.cells import (FINAL_EVAL, SHIELDED_EVAL, Cell, attempt_argv, cell_dir, log_path,
                                       needs_shielded_eval, plan, write_record)
from pe_rlhf.apps.sweeps.methods import PROXY_Q_RECIPES

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass
class SweepReport:
    """What one invocation did: cells skipped (finished before), finished now (seconds), failed (error), stopped
    (killed or left unstarted at a deadline or an interrupt: the process backend)."""

    skipped: list[str] = field(default_factory=list)
    finished: dict[str, float] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    stopped: list[str] = field(default_factory=list)


@contextlib.contextmanager
def _output_to(path: Path):
    """Send this process's stdout and stderr (file descriptors too: native code, subprocesses) to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(path, "a") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
                yield log
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _run_recipe(recipe: str, policy: str | None, argv: list[str], directory: Path) -> None:
    if recipe in PROXY_Q_RECIPES:
        from pe_rlhf.algorithms.proxy_q.recipe import load_recipe_script

        load_recipe_script(recipe).main(argv)  # recipes/<recipe>/train.py: the loop is the script's
    elif recipe == "evaluate":
        _evaluate_only(policy, argv, directory)
    else:
        from pe_rlhf.algorithms.baselines import main as baseline_main

        baseline_main(recipe, argv)


def _evaluate_only(policy: str, argv: list[str], directory: Path) -> None:
    """An evaluation-only cell: ``policy`` on the scenes the recipe's final evaluation uses (its
    ``eval.split`` / ``eval.episodes`` / ``env``), written as the cell's ``final_eval.json``."""
    from pe_rlhf.evaluation import write_json
    from pe_rlhf.runtime.config import save_config
    from pe_rlhf.runtime.recipe import evaluate_reference
    from pe_rlhf.algorithms.proxy_q.config import load_config

    overrides = argv[: argv.index("--out")]
    cfg = load_config(None, overrides)
    save_config(cfg, directory / "config.yaml")
    started = time.time()
    summary = evaluate_reference(policy, cfg)
    summary["training"] = None
    summary["eval_seconds"] = time.time() - started
    write_json(directory / FINAL_EVAL, summary)
    print(f"{policy}: success {summary['success_rate']['mean']:.2f} on {summary['episodes']} episodes")


def evaluate_shielded_cell(directory: Path, threshold: float) -> dict:
    """The finished run in ``directory`` (either kind of recipe) under the runtime shield (``threshold`` seconds) on
    its final evaluation's scenes (its ``eval.split``, ``eval.episodes``, world), written as ``shielded_eval.json``."""
    from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor, saved_run_config
    from pe_rlhf.evaluation import TorchRLPolicyAdapter, write_json
    from pe_rlhf.runtime.recipe import evaluate_shielded

    started = time.time()
    summary = evaluate_shielded(TorchRLPolicyAdapter(load_run_actor(directory)), threshold,
                                saved_run_config(directory), name=f"{directory.name} shielded")
    summary["threshold"] = threshold
    summary["eval_seconds"] = time.time() - started
    write_json(directory / SHIELDED_EVAL, summary)
    print(f"shielded (threshold {threshold:g} s): success {summary['success_rate']['mean']:.2f}, safety violation "
          f"{summary['safety_violation']['mean']:.2f}, the shield drove {summary['override_share']:.3f} of the steps, "
          f"on {summary['episodes']} episodes", flush=True)
    return summary


def run_cell(cell: Cell, out: str, threads: int = 1) -> dict:
    """Run one cell here (the body of its Ray task); returns ``{"name", "seconds", "resumed"}``. A cell whose
    training has finished but whose shielded evaluation is missing gets that evaluation alone."""
    import torch

    for var in THREAD_VARS:
        os.environ[var] = str(threads)
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    torch.set_num_threads(threads)
    directory = cell_dir(Path(out), cell)
    started = time.time()
    with _output_to(log_path(Path(out), cell)):
        trained = (directory / FINAL_EVAL).is_file()
        if trained:
            argv, resumed = [], True
            print(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} {cell.name}: trained, the shielded evaluation",
                  flush=True)
        else:
            argv, resumed = attempt_argv(directory, list(cell.overrides))
            print(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} {cell.name}: "
                  f"{'resume' if resumed else 'start'} {cell.method.recipe} {' '.join(argv)}", flush=True)
        try:
            if not trained:
                _run_recipe(cell.method.recipe, cell.method.policy, argv, directory)
            if needs_shielded_eval(Path(out), cell):
                evaluate_shielded_cell(directory, float(cell.shield))
        except BaseException:
            traceback.print_exc()
            raise
    return {"name": cell.name, "seconds": time.time() - started, "resumed": resumed}


def running_text(names: list[str], width: int = 100) -> str:
    text = "running: " + ", ".join(names)
    return text if len(text) <= width else text[: width - 12] + f"... ({len(names)})"


# Measured 2026-12-01 on 2 cores: two sweep cells (nice 15) beside two single-threaded benchmarks (nice 0) ran at
# 0.6 env steps/s, 14% CPU each; reniced to -5 they went back to 4 steps/s in warm-up.
RAY_WORKER_NICENESS = "RAY_worker_niceness"


def _init_ray(address: str | None):
    """Ray, started here (local) or connected to ``address``; returns (ray, whether we started it)."""
    try:
        import ray
    except ImportError:
        raise RuntimeError("pe-rlhf sweep runs its cells as Ray tasks: pip install 'ray==2.60.0'") from None
    if ray.is_initialized():
        return ray, False
    if address is None:  # a local Ray starts its workers at nice 15: any other job on the machine starves the cells
        os.environ.setdefault(RAY_WORKER_NICENESS, "0")
    ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
    return ray, True


def run_cells(cells: list[Cell], out: str | Path, *, address: str | None = None, max_parallel: int | None = None,
              num_cpus: float = 1.0, progress: bool = True, name: str = "sweep") -> SweepReport:
    """Run every unfinished cell as a Ray task, writing to ``out/<cell>/``; finished cells are skipped.

    ``address``: a Ray cluster (None: the running Ray of this process, else a local one started here and
    shut down after). ``max_parallel``: cells in flight at once (None: as many as the cluster's CPUs hold).
    """
    from tqdm import tqdm

    out = Path(out)
    finished, todo = plan(out, cells)
    report = SweepReport(skipped=[c.name for c in finished])
    if not todo:
        return report
    for cell in todo:
        write_record(out, cell)
    ray, started_here = _init_ray(address)
    try:
        threads = max(1, int(num_cpus))
        env_vars = {"SDL_VIDEODRIVER": "dummy", **{v: str(threads) for v in THREAD_VARS}}
        task = ray.remote(run_cell).options(num_cpus=num_cpus, max_retries=0,
                                            runtime_env={"env_vars": env_vars})
        capacity = max_parallel or max(1, int(ray.cluster_resources().get("CPU", 1) // num_cpus))
        pending, in_flight = list(todo), {}
        bar = tqdm(total=len(cells), initial=len(finished), desc=name, unit="cell", disable=not progress,
                   dynamic_ncols=True)
        while pending or in_flight:
            while pending and len(in_flight) < capacity:
                cell = pending.pop(0)
                in_flight[task.remote(cell, str(out.resolve()), threads)] = cell
            bar.set_postfix_str(running_text([c.name for c in in_flight.values()]))
            done, _ = ray.wait(list(in_flight), num_returns=1)
            for ref in done:
                cell = in_flight.pop(ref)
                try:
                    result = ray.get(ref)
                    report.finished[cell.name] = result["seconds"]
                    resumed = ", resumed" if result["resumed"] else ""
                    bar.write(f"done   {cell.name} ({result['seconds']:.0f} s{resumed})")
                except Exception as e:  # noqa: BLE001 - a failed cell must not stop the others
                    cause = getattr(e, "cause", None) or e
                    lines = str(cause).strip().splitlines()
                    report.failed[cell.name] = f"{type(cause).__name__}: {lines[-1] if lines else ''}"
                    bar.write(f"FAILED {cell.name}: {report.failed[cell.name]} (log: {log_path(out, cell)})")
                bar.update(1)
        bar.set_postfix_str("")
        bar.close()
    finally:
        if started_here:
            ray.shutdown()
    return report
