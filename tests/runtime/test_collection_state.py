"""``pe_rlhf.runtime.collection_state``: the collector's carrier through JSON, exactly."""

from __future__ import annotations

import json

import torch
from tensordict import TensorDict

from pe_rlhf.runtime.collection_state import capture_collection, decode_tensordict, encode_tensordict


def test_a_carrier_survives_json_bit_for_bit():
    carrier = TensorDict({"observation": torch.randn(250), "done": torch.tensor([True]),
                          "action": torch.tensor([float("nan"), 1e-39]),  # NaN, a subnormal float32
                          "collector": {"traj_ids": torch.tensor(7)}, "cost": torch.randn(1, dtype=torch.float64)}, [])
    back = decode_tensordict(json.loads(json.dumps(encode_tensordict(carrier))), carrier.batch_size)
    assert set(back.keys(True, True)) == set(carrier.keys(True, True))
    for key in carrier.keys(True, True):
        a, b = carrier[key], back[key]
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a.nan_to_num(3.0), b.nan_to_num(3.0)), key


def test_nothing_is_captured_without_a_local_collector():
    assert capture_collection(None, None) is None
