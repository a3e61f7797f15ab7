"""The driving world: procedural highway-env scenes as a gymnasium and a TorchRL env."""

from __future__ import annotations

from pe_rlhf import ENV_ID, MAX_EPISODE_STEPS, register_env
from pe_rlhf.envs.action import action_to_controls, controls_to_action
from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.envs.splits import TEST_SEEDS, TRAIN_SEEDS, VALIDATION_SEEDS, parse_seeds, scene_seeds


def register() -> None:
    """Register ``pe_rlhf/Driving-v0`` with gymnasium (idempotent; ``import pe_rlhf`` has done it already)."""
    register_env()


def make_gym_env(config: DrivingConfig | dict | None = None, render_mode: str | None = None):
    """A fresh :class:`~pe_rlhf.envs.driving_env.DrivingEnv` (no gymnasium wrappers)."""
    from pe_rlhf.envs.driving_env import DrivingEnv

    return DrivingEnv(config, render_mode=render_mode)


def make_env(config: DrivingConfig | dict | None = None, render_mode: str | None = None, episode_stats: bool = False):
    """The TorchRL driving env, a ``TransformedEnv`` ready for more transforms (interventions):
    :func:`pe_rlhf.envs.torchrl_env.make_env`, imported on first use so that the gymnasium side and the command
    line start without TorchRL."""
    from pe_rlhf.envs.torchrl_env import make_env as make_torchrl_env

    return make_torchrl_env(config, render_mode=render_mode, episode_stats=episode_stats)


register()

__all__ = [
    "ENV_ID",
    "MAX_EPISODE_STEPS",
    "DrivingConfig",
    "TEST_SEEDS",
    "VALIDATION_SEEDS",
    "TRAIN_SEEDS",
    "action_to_controls",
    "controls_to_action",
    "make_env",
    "make_gym_env",
    "parse_seeds",
    "register",
    "scene_seeds",
]
