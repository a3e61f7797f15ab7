"""Shared test setup: headless pygame, the src layout and the shared helpers on the import path.

Tests mirror the package layout: ``tests/<package>/`` for ``pe_rlhf.<package>``, ``tests/benchmarks/`` and
``tests/examples/`` for the scripts, ``tests/reliability/`` for what survives what; tests of top-level modules
(``durable``, ``filelock``, ``threads``, ``wrappers``) and of the layering sit here.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# Rendering tests (and any pygame import) must not need a display.
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

_SRC = Path(__file__).resolve().parents[1] / "src"
if _SRC.is_dir() and str(_SRC) not in sys.path:
    sys.path.insert(0, str(_SRC))
# The shared helpers (_factories, _scripts, ...) for the tests in every sub-folder (tests/<package>/).
_TESTS = str(Path(__file__).resolve().parent)
if _TESTS not in sys.path:
    sys.path.insert(0, _TESTS)


import pytest  # noqa: E402


def pytest_configure(config):
    """Under pytest-xdist (``make test``: ``-n auto``), each worker takes its share of the cores for torch's
    intra-op threads: N workers each spinning up every core's worth of threads would fight over them."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers > 1:
        import torch

        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


@pytest.fixture
def one_thread():
    """Small nets: one intra-op thread is faster, and immune to oversubscription on a loaded machine."""
    from pe_rlhf.threads import torch_threads

    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def one_thread_module():
    """``one_thread`` for a whole test module (``pytestmark = pytest.mark.usefixtures(...)``)."""
    from pe_rlhf.threads import torch_threads

    with torch_threads(1):
        yield
