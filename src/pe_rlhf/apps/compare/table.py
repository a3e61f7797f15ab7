"""The spec's Table 1 from collected rows: per seed the values (:data:`COLUMNS`, read as the sweep summary
reads a cell: :mod:`pe_rlhf.apps.sweeps.summary`), per row the mean over its seeds and its 95% bootstrap CI
(:mod:`pe_rlhf.evaluation.statistics`),
written as ``table.md`` and ``table.csv``.

Columns, in the paper's order (spec section 7) with the training ones the issue adds:

- ``takeover data``: ``train/takeover_data_usage`` of the last ``metrics.csv`` row (mentor steps / online
  steps), else the training totals' ``takeover_data_usage``, else ``mentor_data_share`` (BC, CQL: 1.0; GAIL:
  demonstrations / all data);
- ``total data``: env steps of training (last ``env_steps``, else the totals') plus recorded demonstration
  steps (``demo_steps``: BC, CQL, GAIL, HG-DAgger, IWR);
- ``training time (min)``: the last ``wall_time`` / 60;
- ``train safety viol.``: ``train/safety_violations_total`` (else the totals' ``safety_violations``) plus the
  demonstrations' (``demo_safety_violations``), the safety cost of all the data the method used;
- test return, success, safety, distance, velocity, overtakes: the ``final_eval.json`` means (the recipe's
  ``eval.split``).

An evaluation-only row (IDM-MOBIL) has the test columns only; a missing value is ``—`` in Markdown, NaN in
the CSV (which also has each column's population std). One seed shows its value without an interval.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pe_rlhf.apps.compare.plots import row_curve
from pe_rlhf.evaluation.statistics import interval_text, seed_stats
from pe_rlhf.apps.compare.rows import TRAINED, Row
from pe_rlhf.apps.sweeps.metrics import METRICS, NAN, Metric, last_csv_row, logged_metrics, metric_values
from pe_rlhf.apps.sweeps.summary import write_csv

TABLE_MD, TABLE_CSV = "table.md", "table.csv"


def _training(final: dict) -> dict:
    return final.get("training") or {}


def _env_steps(final: dict, last: dict) -> float:
    if "env_steps" in last:
        return float(last["env_steps"])
    training = _training(final)
    value = training.get("env_steps", training.get("frames"))
    return float(value) if value is not None else NAN


def _total_data(final: dict, last: dict) -> float:
    return _env_steps(final, last) + float(_training(final).get("demo_steps") or 0.0)


def _train_safety(final: dict, last: dict) -> float:
    online = METRICS["train_safety_violations"].read(final, last)
    return online + float(_training(final).get("demo_safety_violations") or 0.0)


def _minutes(final: dict, last: dict) -> float:
    if "wall_time" in last:
        return float(last["wall_time"]) / 60
    seconds = _training(final).get("wall_time_s")
    return float(seconds) / 60 if seconds is not None else NAN


def _test(key: str, label: str) -> Metric:
    return Metric(label, ".2f", METRICS[key].read)


COLUMNS: dict[str, Metric] = {
    "takeover_data_usage": Metric("takeover data", ".2f", logged_metrics("train/takeover_data_usage",
                                                                  "takeover_data_usage",
                                                                  "mentor_data_share")),
    "total_data": Metric("total data", ".0f", _total_data),
    "train_minutes": Metric("training time (min)", ".1f", _minutes),
    "train_safety_violations": Metric("train safety viol.", ".2f", _train_safety),
    "episodic_return": _test("episodic_return", "test return"),
    "success_rate": _test("success_rate", "success"),
    "safety_violation": _test("safety_violation", "test safety"),
    "travel_distance": _test("travel_distance", "distance m"),
    "travel_velocity": _test("travel_velocity", "velocity km/h"),
    "overtake_count": _test("overtake_count", "overtakes"),
}
TRAINING_COLUMNS = ("takeover_data_usage", "total_data", "train_minutes", "train_safety_violations")


def seed_values(row: Row) -> list[dict[str, float]]:
    """Every :data:`COLUMNS` value of each seed of ``row`` (training columns NaN for an evaluation row)."""
    values = []
    for source in row.sources:
        csv_path = source.metrics_csv if row.kind == TRAINED else None
        last = last_csv_row(csv_path) if csv_path is not None else {}
        seed = metric_values(source.final, last, COLUMNS)
        if row.kind != TRAINED:
            seed.update({k: NAN for k in TRAINING_COLUMNS})
        values.append(seed)
    return values


def aggregate_rows(rows: list[Row]) -> list[dict[str, Any]]:
    """Per row: label, kind, seeds (how many sources), sources and ``{mean, std, lo, hi, n}`` per column."""
    table = []
    for row in rows:
        seeds = seed_values(row)
        table.append({"label": row.label, "kind": row.kind, "seeds": len(row.sources),
                      "sources": [str(s.path) for s in row.sources],
                      **{k: seed_stats([s[k] for s in seeds]) for k in COLUMNS}})
    return table


def markdown_table(table: list[dict[str, Any]]) -> str:
    """``| method | seeds | takeover data | ... | overtakes |``, one line per row."""
    header = ["method", "seeds", *(m.label for m in COLUMNS.values())]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in table:
        cells = [r["label"], str(r["seeds"]), *(interval_text(r[k], m.fmt) for k, m in COLUMNS.items())]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _describe(row: Row) -> str:
    """``label`` (kind, N episodes on SPLIT): `path` (seed S), ..."""
    evaluated = sorted({(s.final.get("episodes"), (s.config.get("eval") or {}).get("split")) for s in row.sources},
                       key=str)
    episodes = ", ".join(f"{n} episodes" + (f" on {split}" if split else "") for n, split in evaluated if n)
    seeds = ", ".join(f"`{s.path}`" + (f" (seed {s.config['seed']})" if "seed" in s.config else "")
                      for s in row.sources)
    return f"- **{row.label}** ({row.kind}{', ' + episodes if episodes else ''}): {seeds}"


def _steps_text(steps: float) -> str:
    return f"{steps / 1000:g}K" if steps >= 1000 else f"{steps:g}"


def periodic_success(row: Row) -> str | None:
    """``"10K 0.00 · 20K 0.40 · 30K 0.50"``: the row's test success at each periodic evaluation logged in
    ``metrics.csv`` (mean over seeds at the env steps all seeds share), or None when none was logged. Shows
    whether a curve has flattened by the end of its budget."""
    curve = row_curve(row, "eval/success_rate_mean")
    if curve is None:
        return None
    steps, mean, _, _ = curve
    return " · ".join(f"{_steps_text(x)} {y:.2f}" for x, y in zip(steps, mean))


def write_table(out: str | Path, rows: list[Row], title: str = "Table 1",
                images: Sequence[tuple[str, str]] = (), notes: list[str] = ()) -> tuple[dict[str, Path], str]:
    """``table.md`` (embedding ``images``: ``(alt text, file name)`` pairs) and ``table.csv`` in ``out``;
    returns ``({name: path}, the Markdown table)``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = aggregate_rows(rows)
    stats = ("mean", "std", "lo", "hi")
    header = ["method", "kind", "seeds", *(f"{k}_{s}" for k in COLUMNS for s in stats), "sources"]
    write_csv(out / TABLE_CSV, header,
               [[r["label"], r["kind"], r["seeds"], *(r[k][s] for k in COLUMNS for s in stats),
                 ";".join(r["sources"])] for r in table])
    md = markdown_table(table)
    text = [f"# {title}", "",
            ("Mean [95% bootstrap CI] over seeds (one seed: its value). Test metrics from each run's "
            "`final_eval.json` (evaluation-only rows: the `pe-rlhf evaluate` JSON); takeover data = mentor steps "
            "/ online steps (offline imitation: the demonstrations' share); total data = env steps + recorded "
            "demonstration steps; training time = the last `wall_time`; train safety viol. = training "
            "violations + the demonstrations'. — = no value."), "", md]
    for alt, name in images:
        text += [f"![{alt.replace('_', ' ')}]({name})", ""]
    text += ["## Rows", "", *(_describe(row) for row in rows)]
    periodic = [(row.label, line) for row in rows if row.kind == TRAINED and (line := periodic_success(row))]
    if periodic:
        text += ["", "## Test success at each periodic evaluation", "",
                 "Mean over seeds at the env steps every seed evaluated at (`eval/success_rate_mean` in "
                 "`metrics.csv`); a curve still rising at its last evaluation has not flattened.", "",
                 *(f"- **{label}**: {line}" for label, line in periodic)]
    if notes:
        text += ["", "## Notes", "", *(f"- {n}" for n in notes)]
    (out / TABLE_MD).write_text("\n".join(text).rstrip() + "\n")
    return {"table_md": out / TABLE_MD, "table_csv": out / TABLE_CSV}, md
