"""pe-rlhf: Physics-enhanced RL with Human Feedback, as TorchRL components."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

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
