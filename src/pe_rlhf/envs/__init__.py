"""The driving world: procedural highway-env scenes as a gymnasium and a TorchRL env."""

from __future__ import annotations

import gymnasium as gym

from pe_rlhf.envs.action import action_to_controls, controls_to_action
from pe_rlhf.envs.config import DrivingConfig
from pe_rlhf.envs.splits import TEST_SEEDS, TRAIN_SEEDS, parse_seeds, scene_seeds

ENV_ID = "pe_rlhf/Driving-v0"


def register() -> None:
    """Register ``pe_rlhf/Driving-v0`` with gymnasium (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="pe_rlhf.envs.driving_env:DrivingEnv")


def make_gym_env(config: DrivingConfig | dict | None = None, render_mode: str | None = None):
    """A fresh :class:`~pe_rlhf.envs.driving_env.DrivingEnv` (no gymnasium wrappers)."""
    from pe_rlhf.envs.driving_env import DrivingEnv

    return DrivingEnv(config, render_mode=render_mode)


register()

__all__ = [
    "ENV_ID",
    "DrivingConfig",
    "TEST_SEEDS",
    "TRAIN_SEEDS",
    "action_to_controls",
    "controls_to_action",
    "make_gym_env",
    "parse_seeds",
    "register",
    "scene_seeds",
]
