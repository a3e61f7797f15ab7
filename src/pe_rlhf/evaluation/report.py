"""Present evaluation summaries: the spec's three-stage rich table, and atomic JSON files."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence, Union

from rich.console import Console
from rich.table import Table

Summary = Mapping[str, Any]  # EvaluationSummary.to_dict()

# (stage, header, JSON key, number format) in the spec's reading order (§6).
STAGE_COLUMNS = (
    ("Stage I", "return", "episodic_return", ".1f"),
    ("Stage I", "success", "success_rate", ".2f"),
    ("Stage II", "safety viol.", "safety_violation", ".2f"),
    ("Stage II", "distance m", "travel_distance", ".1f"),
    ("Stage III", "velocity km/h", "travel_velocity", ".1f"),
    ("Stage III", "overtakes", "overtake_count", ".2f"),
)
FAILURE_COLUMNS = (
    ("crash\nvehicle", "crash_vehicle_rate"),
    ("crash\nobject", "crash_object_rate"),
    ("out of\nroad", "out_of_road_rate"),
    ("timeout", "timeout_rate"),
)


def _cell(stat: Mapping[str, float] | None, fmt: str, sep: str = " ") -> str:
    if not stat:
        return "-"
    return f"{stat['mean']:{fmt}}{sep}± {stat['std']:{fmt}}"


def _rows(summaries: Union[Summary, Sequence[tuple[str, Summary]]]) -> list[tuple[str, Summary]]:
    if isinstance(summaries, Mapping):
        return [(summaries.get("policy") or "policy", summaries)]
    return [(str(name), s) for name, s in summaries]


def summary_tables(summaries: Union[Summary, Sequence[tuple[str, Summary]]],
                   sep: str = " ") -> tuple[Table, Table]:
    """The stage table and the failure-rate table; one row per policy.

    In: one summary dict, or ``[(name, summary_dict), ...]``; ``sep`` goes between
    mean and "± std" (``"\n"`` stacks them for narrow consoles). Out: two rich Tables.
    """
    rows = _rows(summaries)
    episodes = sorted({int(s.get("episodes", 0)) for _, s in rows})
    caption = (f"{'/'.join(map(str, episodes))} episodes, mean ± std; failed v/o/r/t: "
               "crash vehicle/object, out of road, timeout")
    stages = Table(title="Evaluation", show_edge=False)
    stages.add_column("policy", style="bold", overflow="fold")
    for stage, header, _, _ in STAGE_COLUMNS:
        stages.add_column(f"{stage}\n{header}", justify="right")
    failures = Table(title="Failure modes (rates)", caption=caption, show_edge=False)
    failures.add_column("policy", style="bold", overflow="fold")
    for header, _ in FAILURE_COLUMNS:
        failures.add_column(header, justify="right")
    failures.add_column("failed\nv/o/r/t", justify="right")
    for name, s in rows:
        stages.add_row(name, *(_cell(s.get(key), fmt, sep) for _, _, key, fmt in STAGE_COLUMNS))
        fb = s.get("failure_breakdown", {})
        counts = "/".join(str(fb.get(k, 0)) for k in ("crash_vehicle", "crash_object", "out_of_road", "timeout"))
        failures.add_row(name, *(_cell(s.get(key), ".2f", sep) for _, key in FAILURE_COLUMNS), counts)
    return stages, failures


def print_summary(summaries: Union[Summary, Sequence[tuple[str, Summary]]],
                  console: Console | None = None) -> None:
    """Print the three-stage table then the failure rates. In: one summary dict or ``[(name, dict)]``."""
    console = console or Console()
    tables = summary_tables(summaries)
    unbounded = console.options.update(max_width=10_000)  # measure() clamps to the console otherwise
    if any(console.measure(t, options=unbounded).maximum > console.width for t in tables):
        tables = summary_tables(summaries, sep="\n")  # stacked cells fit; squeezed ones read "overt…"
    for table in tables:
        console.print(table)


def write_json(path: str | os.PathLike, summary: Summary) -> Path:
    """Write ``summary`` as indented JSON atomically (temp file in the same dir, then os.replace).

    Creates missing parent directories. Out: the written path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(summary, f, indent=2)
            f.write("\n")
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files; a report should be readable like any other
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path
