"""Sweeps: a base recipe config crossed with a grid (method x mentor x parameter x seed), each cell a Ray
task, resumable, summarised into one folder.

    pe-rlhf sweep recipes/sweeps/mentor_proficiency.yaml [--out DIR] [--address ADDR] [--max-parallel N] [--dry-run]

Parts: :mod:`~pe_rlhf.apps.sweeps.spec` (the YAML config, checked), :mod:`~pe_rlhf.apps.sweeps.methods` (method ->
recipe entry + overrides), :mod:`~pe_rlhf.apps.sweeps.cells` (grid expansion, names, on-disk bookkeeping),
:mod:`~pe_rlhf.apps.sweeps.execution` (Ray tasks, progress), :mod:`~pe_rlhf.apps.sweeps.summary` (``cells.csv``,
``summary.csv``, ``summary.md``) and :mod:`~pe_rlhf.apps.sweeps.plots`.

Folder layout: ``OUT/sweep.yaml`` (the config as given), ``OUT/<cell>/`` (the recipe's run folder plus
``cell.json``), ``OUT/logs/<cell>.log``, ``OUT/cells.csv``, ``OUT/summary.{md,csv,png}``,
``OUT/value_takeover_rate.png``, ``OUT/takeover_rate.png``.
"""

from __future__ import annotations

from pathlib import Path

from pe_rlhf.apps.sweeps.cells import Cell, check_cell_configs, expand
from pe_rlhf.apps.sweeps.execution import SweepReport, run_cells
from pe_rlhf.apps.sweeps.spec import SweepConfigError, SweepSpec, load_sweep, parse_sweep
from pe_rlhf.apps.sweeps.summary import DEFAULT_METRICS, METRICS, write_summary

DEFAULT_ROOT = Path("runs") / "sweeps"


def run_sweep(spec: SweepSpec, out: str | Path | None = None, *, address: str | None = None,
              max_parallel: int | None = None, progress: bool = True) -> SweepReport:
    """Check every cell's config, run the unfinished cells, write the summary; returns what ran."""
    out = Path(out) if out is not None else DEFAULT_ROOT / spec.name
    cells = expand(spec)
    check_cell_configs(cells)
    out.mkdir(parents=True, exist_ok=True)
    report = run_cells(cells, out, address=address, max_parallel=max_parallel, num_cpus=spec.num_cpus,
                       progress=progress, name=spec.name)
    write_summary(out, cells, spec.metrics, title=spec.name, description=spec.description)
    return report


__all__ = ["DEFAULT_METRICS", "METRICS", "Cell", "SweepConfigError", "SweepReport", "SweepSpec", "check_cell_configs",
           "expand", "load_sweep", "parse_sweep", "run_cells", "run_sweep", "write_summary"]
