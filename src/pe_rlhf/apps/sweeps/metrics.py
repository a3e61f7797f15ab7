"""The columns a sweep's tables can show: :data:`METRICS` (header, number format, how to read it from a
cell's ``final_eval.json`` (with its ``shielded_eval.json`` under ``"shielded"`` where the sweep shields) and the
last row of its ``metrics.csv``) and the default selection
:data:`DEFAULT_METRICS`. A module of its own, so that the sweep spec, the summary and the plots share it
without importing one another.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

NAN = float("nan")


@dataclass(frozen=True)
class Metric:
    """A summary column: its header, number format and how to read it from ``(final_eval, last_csv_row)``."""

    label: str
    fmt: str
    read: Callable[[dict, dict], float]


def _test(key: str) -> Callable[[dict, dict], float]:
    return lambda final, last: float((final.get(key) or {}).get("mean", NAN))


def _shielded(key: str) -> Callable[[dict, dict], float]:
    """The mean of ``key`` in the cell's evaluation under the runtime shield (NaN where it was not shielded)."""
    def read(final: dict, last: dict) -> float:
        value = (final.get("shielded") or {}).get(key, NAN)
        return float(value["mean"] if isinstance(value, dict) else value)
    return read


def logged_metrics(column: str, *training_keys: str) -> Callable[[dict, dict], float]:
    """``column`` of the last metrics row, else the first of ``training_keys`` in ``final["training"]``."""
    def read(final: dict, last: dict) -> float:
        if column in last:
            return float(last[column])
        training = final.get("training") or {}
        return next((float(training[k]) for k in training_keys if training.get(k) is not None), NAN)
    return read


METRICS: dict[str, Metric] = {
    "success_rate": Metric("test success", ".2f", _test("success_rate")),
    "safety_violation": Metric("test safety viol.", ".2f", _test("safety_violation")),
    "episodic_return": Metric("test return", ".1f", _test("episodic_return")),
    "route_completion": Metric("test route completion", ".2f", _test("route_completion")),
    "travel_distance": Metric("test distance m", ".1f", _test("travel_distance")),
    "travel_velocity": Metric("test velocity km/h", ".1f", _test("travel_velocity")),
    "overtake_count": Metric("test overtakes", ".2f", _test("overtake_count")),
    "train_safety_violations": Metric("train safety viol.", ".1f",
                                      logged_metrics("train/safety_violations_total", "safety_violations")),
    "takeover_data_usage": Metric("takeover data usage", ".2f", logged_metrics("train/takeover_data_usage")),
    "value_takeover_rate": Metric("value-takeover rate", ".2f", logged_metrics("train/value_takeover_rate")),
    # where the final evaluation's episodes end (rates over its episodes; success is the rest)
    "crash_vehicle_rate": Metric("crash vehicle", ".2f", _test("crash_vehicle_rate")),
    "crash_object_rate": Metric("crash object", ".2f", _test("crash_object_rate")),
    "out_of_road_rate": Metric("out of road", ".2f", _test("out_of_road_rate")),
    "timeout_rate": Metric("timeout", ".2f", _test("timeout_rate")),
    # the trained actor under the runtime shield on the same scenes (a sweep with ``shield``)
    "shielded_success_rate": Metric("shielded success", ".2f", _shielded("success_rate")),
    "shielded_safety_violation": Metric("shielded safety viol.", ".2f", _shielded("safety_violation")),
    "override_share": Metric("shield override share", ".3f", _shielded("override_share")),
    "train_wall_minutes": Metric("train wall min", ".1f",
                                 lambda final, last: float(last["wall_time"]) / 60 if "wall_time" in last else NAN),
}
DEFAULT_METRICS = ("success_rate", "safety_violation", "train_safety_violations", "takeover_data_usage",
                   "value_takeover_rate")


def last_csv_row(path: Path) -> dict[str, float]:
    if not path.is_file():
        return {}
    from pe_rlhf.runtime.metrics_logger import read_metrics_csv

    _, rows = read_metrics_csv(path)
    return rows[-1] if rows else {}


def metric_values(final: dict, last: dict, metrics: dict[str, Metric] = METRICS) -> dict[str, float]:
    """Every metric's value from a ``final_eval.json`` dict and the last ``metrics.csv`` row (NaN where none)."""
    values = {}
    for key, metric in metrics.items():
        try:
            values[key] = metric.read(final, last)
        except (TypeError, ValueError, AttributeError):
            values[key] = NAN
    return values


__all__ = ["DEFAULT_METRICS", "METRICS", "NAN", "Metric", "last_csv_row", "logged_metrics", "metric_values"]
