"""The sweep table columns read what a cell's final evaluation and last metrics row say."""

from __future__ import annotations

import math

from pe_rlhf.apps.sweeps.metrics import METRICS, metric_values


def test_failure_mode_columns_read_the_final_evaluation_rates():
    final = {"success_rate": {"mean": 0.5}, "crash_vehicle_rate": {"mean": 0.1}, "crash_object_rate": {"mean": 0.05},
             "out_of_road_rate": {"mean": 0.25}, "timeout_rate": {"mean": 0.1}}
    values = metric_values(final, {"train/takeover_data_usage": 0.3})
    assert (values["crash_vehicle_rate"], values["crash_object_rate"], values["out_of_road_rate"],
            values["timeout_rate"]) == (0.1, 0.05, 0.25, 0.1)
    assert values["success_rate"] + sum(values[k] for k in ("crash_vehicle_rate", "crash_object_rate",
                                                            "out_of_road_rate", "timeout_rate")) == 1.0
    assert values["takeover_data_usage"] == 0.3
    assert math.isnan(metric_values({}, {})["timeout_rate"])  # a cell without an evaluation: not a number
    assert METRICS["timeout_rate"].label == "timeout"
