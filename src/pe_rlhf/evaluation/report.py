"""Present evaluation summaries: the spec's three-stage rich table, and atomic JSON files."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence, Union

from rich.console import Console
from rich.table import Table

from pe_rlhf import durable

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
LABEL_WIDTH = 36  # a policy label's most characters (fit_label): one line beside the numbers
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


GENERIC_PARTS = ("checkpoints", "actor.safetensors", "actor.pt", "latest")  # path parts that do not tell runs apart


def fit_label(name: str, max_width: int = LABEL_WIDTH) -> str:
    """A table label for ``name`` that fits on one line of ``max_width`` characters.

    A label naming a path (``agent:/long/path/to/runs/pe-rlhf__professional__s0``) keeps its prefix
    and the path's last telling part (``agent:pe-rlhf__professional__s0``; ``checkpoints``,
    ``ckpt_*`` and ``actor.pt`` take their parent along); what is still too long loses the prefix,
    then its start (``…``). Other labels pass unchanged if they fit. The JSON keeps the full name.
    """
    prefix, sep, rest = name.partition(":")
    if not sep or len(prefix) < 2 or not prefix.isidentifier():  # no "agent:"-style prefix (a drive, "C:", is none)
        prefix, sep, rest = "", "", name
    if "/" in rest or os.sep in rest:
        parts = [p for p in Path(rest).parts if p not in ("", "/", os.sep)]
        tail = parts[-1:] if parts else [rest]
        while len(tail) < len(parts) and (tail[0] in GENERIC_PARTS or tail[0].startswith("ckpt_")):
            tail = parts[-len(tail) - 1:]
        rest = "/".join(tail)
    label = f"{prefix}{sep}{rest}"
    if len(label) > max_width:
        label = rest  # the run's name tells rows apart; its prefix goes first
    return label if len(label) <= max_width else "…" + label[-(max_width - 1):]


def _rows(summaries: Union[Summary, Sequence[tuple[str, Summary]]], label_width: int) -> list[tuple[str, Summary]]:
    if isinstance(summaries, Mapping):
        return [(fit_label(summaries.get("policy") or "policy", label_width), summaries)]
    return [(fit_label(str(name), label_width), s) for name, s in summaries]


def summary_tables(summaries: Union[Summary, Sequence[tuple[str, Summary]]],
                   sep: str = " ", label_width: int = LABEL_WIDTH) -> tuple[Table, Table]:
    """The stage table and the failure-rate table; one row per policy.

    In: one summary dict, or ``[(name, summary_dict), ...]``; ``sep`` goes between
    mean and "± std" (``"\n"`` stacks them for narrow consoles); ``label_width``: the policy labels'
    most characters (:func:`fit_label`, one line each). Out: two rich Tables.
    """
    rows = _rows(summaries, label_width)
    episodes = sorted({int(s.get("episodes", 0)) for _, s in rows})
    caption = (f"{'/'.join(map(str, episodes))} episodes, mean ± std; failed v/o/r/t: "
               "crash vehicle/object, out of road, timeout")
    stages = Table(title="Evaluation", show_edge=False)
    stages.add_column("policy", style="bold", no_wrap=True)
    for stage, header, _, _ in STAGE_COLUMNS:
        stages.add_column(f"{stage}\n{header}", justify="right")
    failures = Table(title="Failure modes (rates)", caption=caption, show_edge=False)
    failures.add_column("policy", style="bold", no_wrap=True)
    for header, _ in FAILURE_COLUMNS:
        failures.add_column(header, justify="right")
    failures.add_column("failed\nv/o/r/t", justify="right", no_wrap=True)
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
    unbounded = console.options.update(max_width=10_000)  # measure() clamps to the console otherwise

    def fits(candidate: tuple[Table, Table]) -> bool:
        return all(console.measure(t, options=unbounded).maximum <= console.width for t in candidate)

    # Side-by-side cells, then stacked ones ("overt…" is what squeezing does), each with the labels
    # shortened step by step: the first layout that fits the console wins.
    layouts = [(sep, width) for sep in (" ", "\n") for width in (LABEL_WIDTH, 28, 20, 14, 10)]
    tables = next((t for t in (summary_tables(summaries, sep, width) for sep, width in layouts) if fits(t)),
                  summary_tables(summaries, "\n", 10))
    for table in tables:
        console.print(table)


def write_json(path: str | os.PathLike, summary: Summary) -> Path:
    """Write ``summary`` as indented JSON atomically (:func:`pe_rlhf.durable.replace_bytes`).

    Creates missing parent directories. Out: the written path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    durable.replace_bytes(path, (json.dumps(summary, indent=2) + "\n").encode())
    return path
