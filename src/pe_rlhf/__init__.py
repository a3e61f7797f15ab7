"""pe-rlhf: Physics-enhanced RL with Human Feedback, as TorchRL components.

Importing it registers the driving env with gymnasium, ``gymnasium.make("pe_rlhf/Driving-v0")``, and nothing
heavier: the env's module (highway-env, pygame) loads on the first ``make``.
"""

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

ENV_ID = "pe_rlhf/Driving-v0"
# gymnasium's TimeLimit for ENV_ID: the default DrivingConfig.horizon (policy steps; the env truncates itself at
# its own horizon too). Written out here so that the registration needs no import of the env (highway-env takes
# seconds); tests/test_gym_registration.py checks that the two agree. A longer horizon needs
# gymnasium.make(ENV_ID, config={"horizon": n}, max_episode_steps=n).
MAX_EPISODE_STEPS = 1000


def register_env() -> None:
    """Register :data:`ENV_ID` with gymnasium (idempotent; ``import pe_rlhf`` calls it). Without gymnasium on the
    path (``python -S``, which reads only the version) there is nothing to register with."""
    try:
        from gymnasium.envs.registration import register, registry
    except ImportError:
        return

    if ENV_ID not in registry:
        register(id=ENV_ID, entry_point="pe_rlhf.envs.driving_env:DrivingEnv", max_episode_steps=MAX_EPISODE_STEPS)


register_env()
