"""pe-rlhf: Physics-enhanced RL with Human Feedback, as TorchRL components."""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

# OpenMP threads that sleep at barriers rather than spin: on a shared machine a spinning update thread
# fights the other jobs for its core and every update waits for it (pe_rlhf.threads). Read once, when
# torch's OpenMP runtime loads: effective when pe_rlhf is imported before torch.
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

DISTRIBUTION = "pe-rlhf"  # [project] name in pyproject.toml


def _version() -> str:
    """The installed distribution's version; in a source checkout that is not installed (``src/`` on
    ``PYTHONPATH``), the version in the checkout's ``pyproject.toml``: pyproject.toml is the one source."""
    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        pass
    import tomllib

    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    try:
        with open(pyproject, "rb") as f:
            return str(tomllib.load(f)["project"]["version"])
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "0+unknown"


__version__ = _version()
