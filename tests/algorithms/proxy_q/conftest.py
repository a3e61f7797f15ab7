"""Fixtures shared by the modules of ``tests/algorithms/proxy_q/``."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def sac_run(tmp_path_factory):
    """The run folder of ``recipes/sac_rs/train.py profile=smoke``, read (never written) by ``test_expert_warmup``
    and ``test_value_expert``: one run for both where they share a process."""
    from pe_rlhf.algorithms.baselines import main as baseline_main
    from pe_rlhf.threads import torch_threads

    out = tmp_path_factory.mktemp("sac_rs")
    with torch_threads(1):  # tiny nets: one thread
        baseline_main("sac_rs", ["profile=smoke", "--out", str(out)])
    return out
