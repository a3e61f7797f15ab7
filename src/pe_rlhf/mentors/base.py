"""The one mentor interface: simulated and real mentors are interchangeable.

A mentor watches the scene and the agent's proposed action and answers
``MentorDecision(takeover, action)``: whether it holds control this step and the
action it would execute. Every transform and recipe takes any :class:`Mentor`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class MentorDecision:
    """A mentor's answer for one step.

    ``takeover``: the mentor holds control this step. ``action``: float32 ``(2,)``
    ``[steering, throttle]`` in [-1, 1], the mentor's own action (meaningful even
    when it does not take over: the physics/hybrid selector may compare against it).
    """

    takeover: bool
    action: np.ndarray


class Mentor(ABC):
    """Base class of every mentor (simulated driver or a person at the controls).

    ``env`` arguments are the :class:`~pe_rlhf.envs.driving_env.DrivingEnv` (the
    simulator; a real person sees it through the window, a simulated mentor reads its
    true state). Mentors are stateful (takeover spans, fatigue): ``reset`` at each
    episode start, and ``state_dict``/``load_state_dict`` carry state across a resumed run.
    """

    name: str = "mentor"

    def reset(self, env) -> None:
        """Called after every ``env.reset``."""

    def reseed(self, seed: int) -> None:
        """Start over as if built with ``seed`` (a seeded ``env.reset(seed=)`` calls it through
        :class:`~pe_rlhf.wrappers.InterventionWrapper`): same seed, same decisions. A mentor without random
        numbers or state across episodes has nothing to do (the default)."""

    @abstractmethod
    def act(self, env) -> np.ndarray:
        """The mentor's own action for the current state (driving alone)."""

    @abstractmethod
    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        """Whether to take over given the agent's proposal, and the mentor's action."""

    def __call__(self, env, agent_action: np.ndarray) -> tuple[bool, np.ndarray]:
        d = self.decide(env, np.asarray(agent_action, dtype=np.float32))
        return d.takeover, d.action

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state:
            raise ValueError(f"{type(self).__name__} has no state to load, got keys {sorted(state)}")
