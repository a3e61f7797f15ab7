"""Test helpers importable by ``ParallelEnv`` workers: a real-driver mentor and an env factory."""

from __future__ import annotations

import numpy as np

from pe_rlhf.envs.torchrl_env import make_env
from pe_rlhf.mentors import Mentor, MentorDecision, PrivilegedDriver
from pe_rlhf.transforms import InterventionTransform

# Small, fast world: light traffic, short episodes.
FAST_CONFIG = {"traffic_density": 0.3, "obstacle_density": 0.5, "min_blocks": 2, "max_blocks": 2, "horizon": 60}


class DriverMentor(Mentor):
    """A real driver (``PrivilegedDriver``) that takes over when the agent's action differs from its own
    by more than ``tolerance`` in any dimension (deterministic)."""

    name = "driver"

    def __init__(self, tolerance: float = 0.5):
        self.driver = PrivilegedDriver()
        self.tolerance = tolerance
        self.resets = 0

    def reset(self, env) -> None:
        self.driver.reset()
        self.resets += 1

    def act(self, env) -> np.ndarray:
        return self.driver(env)

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        own = self.act(env)
        return MentorDecision(bool(np.any(np.abs(agent_action - own) > self.tolerance)), own)


def make_intervention_env(config: dict | None = None):
    """``make_env`` + ``InterventionTransform`` with its own mentor (HACO mode), one per worker."""
    env = make_env({**FAST_CONFIG, **(config or {})})
    env.append_transform(InterventionTransform(DriverMentor()))
    return env
