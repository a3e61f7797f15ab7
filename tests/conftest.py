"""Shared test setup: headless pygame and the src layout on the import path."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# Rendering tests (and any pygame import) must not need a display.
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

_SRC = Path(__file__).resolve().parents[1] / "src"
if _SRC.is_dir() and str(_SRC) not in sys.path:
    sys.path.insert(0, str(_SRC))


import pytest  # noqa: E402


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
