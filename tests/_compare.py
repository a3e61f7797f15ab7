"""Exact (bitwise) comparison of nested run state, shared by the checkpoint and kill/resume tests."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase


def assert_same(a, b, where: str = "") -> None:
    """Exact equality of nested dicts/lists/tuples/tensors/TensorDicts; ``where`` names the path on failure."""
    if isinstance(a, TensorDictBase):
        assert isinstance(b, TensorDictBase) and a.batch_size == b.batch_size, where
        assert set(a.keys(True, True)) == set(b.keys(True, True)), where
        for key in a.keys(True, True):
            assert torch.equal(a[key], b[key]), f"{where}.{key}"
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), (where, set(a) ^ set(b))
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, (where, a, b)
