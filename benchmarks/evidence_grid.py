"""Issue 21's evidence grid in one command: every experiment's sweep, then its table, figure and claims, each from
that sweep's own cells (mean and 95% bootstrap CI over seeds).

    python benchmarks/evidence_grid.py --dry-run                      # the cells, their state and the cost
    python benchmarks/evidence_grid.py --max-parallel 2               # run what is unfinished, then summarise
    python benchmarks/evidence_grid.py --only physics_ablation --only loss_ablations
    python benchmarks/evidence_grid.py --summarise-only               # the tables from the cells there are

Run from the repository root (the warm-up sweep reads the SAC-RS expert at ``runs/experts/sac_rs_seed0``: when
it is missing, a copy of the one the grid used, kept in ``docs/results/claims/warmup/expert_sac_rs_seed0``, or
one trained here when that is gone too). Sweeps run with ``pe-rlhf sweep`` (``--backend processes`` by default:
no Ray needed), into ``--runs/<sweep>``, resumable: a rerun continues where the last one stopped. Summaries go
to ``--out/<experiment>/``: ``summary.{md,csv,png}`` (:func:`pe_rlhf.apps.sweeps.tables.summarise_cells`, paired
by seed against the experiment's reference row where it has one), and for the claims ``summary.json`` with the
four claims (professional, amateur, adversarial, collapsing; :func:`pe_rlhf.apps.sweeps.claims.write_claims`,
the collapsing claim with the training violations after the switch at 15K) and the value-takeover curves
(``value_takeover.{png,json}``, the paper's Fig. 18 in kind).

The cost (``--dry-run``): cells to train x ``--minutes-per-cell`` (default 25: a 30K-step cell with two side
by side on the 2-core machine of 2026-12, one core each; evaluation-only cells cost about a minute).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from typing import NamedTuple
from pathlib import Path

EXPERT = Path("runs/experts/sac_rs_seed0")
KEPT_EXPERT = Path("docs/results/claims/warmup/expert_sac_rs_seed0")  # the one the grid's warm-up cells used
EXPERT_COMMAND = [sys.executable, "recipes/sac_rs/train.py", "profile=cpu", "seed=0", "env.lane_features=true",
                  "collector.total_frames=30000", "eval.every_frames=0", "eval.episodes=50", "--out", str(EXPERT)]
COLLAPSE_STEP = 15000
MENTORS_FOR_CURVES = ("professional", "amateur")


class Experiment(NamedTuple):
    """One of the issue's experiments: the sweeps it runs, how its table is made."""

    name: str
    title: str
    sweeps: tuple[str, ...]
    paired_against: str | None = None
    needs_expert: bool = False
    claims: bool = False
    metrics: tuple[str, ...] = ("success_rate", "safety_violation", "train_safety_violations", "takeover_data_usage",
                                "value_takeover_rate", "travel_velocity")


EXPERIMENTS = (
    Experiment("claims", "Mentor proficiency, the adversarial and the collapsing mentor (Table 3, the lower bound)",
               ("mentor_proficiency", "claims_adversarial", "claims_collapsing"), claims=True),
    Experiment("physics_ablation", "Physics ablation (Table 2)", ("physics_ablation",), paired_against="idm+mobil"),
    Experiment("loss_ablations", "Loss ablations (Table 4)", ("loss_ablations",), paired_against="full"),
    Experiment("epsilon_sensitivity", "epsilon_select sensitivity (Fig. 20)", ("epsilon_sensitivity",),
               paired_against="epsilon_select=-0.5"),
    Experiment("warmup", "Warm-up strategy and size (Fig. 19)", ("warmup",), paired_against="warmup_steps=10000",
               needs_expert=True),
    Experiment("table1_rlhf", "Table 1's RLHF rows", ("table1_rlhf",)),
)
BY_NAME = {e.name: e for e in EXPERIMENTS}


def sweep_config(sweep: str) -> Path:
    return Path("recipes/sweeps") / f"{sweep}.yaml"


def grid_cost(experiments, runs: Path, minutes_per_cell: float) -> tuple[list[str], float]:
    """One line per sweep (cells, trained, finished) and the core-hours of its unfinished training cells."""
    from pe_rlhf.apps.sweeps import expand, load_sweep
    from pe_rlhf.apps.sweeps.cells import is_finished

    lines, hours = [], 0.0
    for experiment in experiments:
        if experiment.needs_expert and not (EXPERT / "final_eval.json").is_file() and not KEPT_EXPERT.is_dir():
            hours += minutes_per_cell / 60
            lines.append(f"{experiment.name:20s} {'(its expert)':20s}   1 SAC-RS run, not trained yet; "
                         f"{minutes_per_cell / 60:5.1f} core-hours to go")
        for sweep in experiment.sweeps:
            cells = expand(load_sweep(sweep_config(sweep)))
            trained = [c for c in cells if c.method.recipe != "evaluate"]
            todo = [c for c in trained if not is_finished(runs / sweep, c)]
            cost = len(todo) * minutes_per_cell / 60
            hours += cost
            lines.append(f"{experiment.name:20s} {sweep:20s} {len(cells):3d} cells, {len(trained):3d} trained, "
                         f"{len(trained) - len(todo):3d} of them finished; {cost:5.1f} core-hours to go")
    return lines, hours


def run_sweep(sweep: str, runs: Path, args: argparse.Namespace) -> int:
    from pe_rlhf.apps.cli import main as cli

    argv = ["sweep", str(sweep_config(sweep)), "--out", str(runs / sweep), "--backend", args.backend]
    if args.max_parallel:
        argv += ["--max-parallel", str(args.max_parallel)]
    return cli(argv)


def ensure_expert() -> None:
    """The warm-up sweep's expert policy (a SAC-RS run with the env reward): the kept one copied in, else trained
    here."""
    if (EXPERT / "final_eval.json").is_file():
        return
    if (KEPT_EXPERT / "actor.pt").is_file():
        import shutil

        print(f"the warm-up expert: a copy of {KEPT_EXPERT}", flush=True)
        shutil.copytree(KEPT_EXPERT, EXPERT, dirs_exist_ok=True)
        return
    print(f"training the warm-up expert: {' '.join(EXPERT_COMMAND)}", flush=True)
    subprocess.run(EXPERT_COMMAND, check=True)


def summarise(experiment: Experiment, runs: Path, out: Path) -> list[Path]:
    """The experiment's tables and figures in ``out/<name>/`` from the finished cells; returns what it wrote."""
    from pe_rlhf.apps.sweeps.claims import add_violations_after, write_claims
    from pe_rlhf.apps.sweeps.tables import summarise_cells

    target = out / experiment.name
    sources = [runs / s / "cells.csv" for s in experiment.sweeps if (runs / s / "cells.csv").is_file()]
    if not sources:
        print(f"{experiment.name}: no cells yet ({', '.join(experiment.sweeps)} not run)")
        return []
    summarise_cells(sources, target, list(experiment.metrics), title=experiment.title,
                    paired_against=experiment.paired_against)
    written = [target / "summary.md"]
    if experiment.claims:
        collapsing = runs / "claims_collapsing"
        if (collapsing / "cells.csv").is_file():
            after = target / "cells_collapsing_after.csv"
            add_violations_after(collapsing, COLLAPSE_STEP, after)
            sources = [s for s in sources if s.parent != collapsing] + [after]
        write_claims(sources, target)
        written.append(target / "summary.json")
        curves = value_takeover_runs(runs / "mentor_proficiency")
        if curves:
            load_benchmark("value_takeover_curves").main(
                [f"{label}={path}" for label, path in curves] +
                ["--out", str(target / "value_takeover.png"), "--json", str(target / "value_takeover.json")])
            written.append(target / "value_takeover.png")
    return written


def value_takeover_runs(sweep: Path) -> list[tuple[str, Path]]:
    """``(label, run folder)`` of every finished PE-RLHF cell of the mentor-proficiency sweep."""
    return [(f"{mentor} s{run.name.rsplit('__s', 1)[1]}", run)
            for mentor in MENTORS_FOR_CURVES
            for run in sorted(sweep.glob(f"pe-rlhf__{mentor}__s*")) if (run / "final_eval.json").is_file()]


def load_benchmark(name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", choices=list(BY_NAME), metavar="EXPERIMENT",
                        help=f"run only these experiments (repeatable): {', '.join(BY_NAME)}")
    parser.add_argument("--runs", type=Path, default=Path("runs/sweeps"), help="where the sweeps run")
    parser.add_argument("--out", type=Path, default=Path("docs/results/grid"), help="where the tables go")
    parser.add_argument("--backend", choices=("processes", "ray"), default="processes")
    parser.add_argument("--max-parallel", type=int, default=None, metavar="N")
    parser.add_argument("--minutes-per-cell", type=float, default=25.0, metavar="MIN")
    parser.add_argument("--dry-run", action="store_true", help="the cells, their state and the cost; run nothing")
    parser.add_argument("--summarise-only", action="store_true", help="no training: tables from the finished cells")
    args = parser.parse_args(argv)
    if not Path("recipes/sweeps").is_dir():
        parser.error("run from the repository root (recipes/sweeps/ not found here)")
    if args.minutes_per_cell <= 0:
        parser.error(f"--minutes-per-cell {args.minutes_per_cell}: must be > 0")
    experiments = [BY_NAME[n] for n in args.only] if args.only else list(EXPERIMENTS)
    lines, hours = grid_cost(experiments, args.runs, args.minutes_per_cell)
    print("\n".join(lines))
    print(f"to go: {hours:.1f} core-hours at {args.minutes_per_cell:g} min a training cell")
    if args.dry_run:
        return 0
    failed = 0
    for experiment in experiments:
        if not args.summarise_only:
            if experiment.needs_expert:
                ensure_expert()
            for sweep in experiment.sweeps:
                failed += run_sweep(sweep, args.runs, args) != 0
        for path in summarise(experiment, args.runs, args.out):
            print(f"wrote {path}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
