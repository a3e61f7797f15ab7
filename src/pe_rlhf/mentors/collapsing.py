"""A mentor whose quality collapses mid-run: one skill preset for the first ``switch_step`` env steps,
another from then on (the lower-bound experiment: a professional turning adversarial halfway).

The simulated presets degrade only smoothly (fatigue, :mod:`pe_rlhf.mentors.simulated`); this wrapper
makes the change abrupt and its step configurable. Build it by name::

    make_mentor("collapsing", seed, switch_step=15000, before="professional", after="adversarial")

or in a recipe: ``mentor.name=collapsing mentor.kwargs.switch_step=15000``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.simulated import ALIASES, PRESETS, SimulatedMentor, preset

COLLAPSING_KWARGS = ("switch_step", "before", "after")


class CollapsingMentor(Mentor):
    """``before`` (a preset name) drives the first ``switch_step`` env steps it is consulted on, ``after``
    every step from then on.

    A step counts once per env step (``act`` and ``decide`` on the same step count one), across episodes:
    in training that is warm-up plus online steps. Each profile is its own :class:`SimulatedMentor`
    (seeded ``seed``), so the collapsed mentor starts fresh (no inherited fatigue). ``active`` is the one
    in charge now; ``state_dict`` carries the step count and both mentors across a resumed run.
    """

    name = "collapsing"

    def __init__(self, switch_step: int = 15_000, before: str = "professional", after: str = "adversarial",
                 seed: int = 0):
        if isinstance(switch_step, bool) or not isinstance(switch_step, (int, np.integer)) or switch_step < 0:
            raise ValueError(f"CollapsingMentor.switch_step={switch_step!r} is invalid: must be an integer >= 0")
        for field, value in (("before", before), ("after", after)):
            if ALIASES.get(value, value) not in PRESETS:
                raise ValueError(f"CollapsingMentor.{field}={value!r} is invalid: allowed: "
                                 f"{sorted(PRESETS) + sorted(ALIASES)}")
        self.switch_step = int(switch_step)
        self.before = SimulatedMentor(preset(before), seed=seed, name=ALIASES.get(before, before))
        self.after = SimulatedMentor(preset(after), seed=seed, name=ALIASES.get(after, after))
        self.steps = 0  # env steps consulted on so far
        self._road, self._env_step = None, None

    @property
    def active(self) -> SimulatedMentor:
        """The mentor driving the current step (``steps`` counts it already)."""
        return self.before if self.steps <= self.switch_step else self.after

    @property
    def collapsed(self) -> bool:
        return self.steps > self.switch_step

    def _tick(self, env) -> None:
        sim = getattr(env, "unwrapped", env)
        if sim.road is not self._road or sim.steps != self._env_step:
            self.steps += 1
            self._road, self._env_step = sim.road, sim.steps

    def reseed(self, seed: int) -> None:
        """As built with ``seed``: both mentors reseeded, the step count back to 0 (not yet collapsed)."""
        self.before.reseed(seed)
        self.after.reseed(seed)
        self.steps = 0
        self._road, self._env_step = None, None

    def reset(self, env) -> None:
        """Episode start for both (the idle one must not carry a stale episode into the switch)."""
        self.before.reset(env)
        self.after.reset(env)

    def act(self, env) -> np.ndarray:
        self._tick(env)
        return self.active.act(env)

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        self._tick(env)
        return self.active.decide(env, agent_action)

    def state_dict(self) -> dict[str, Any]:
        return {"switch_step": self.switch_step, "steps": self.steps,
                "before": self.before.state_dict(), "after": self.after.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if int(state["switch_step"]) != self.switch_step:
            raise ValueError(f"state was saved by a CollapsingMentor switching at step {state['switch_step']}, "
                             f"this one switches at {self.switch_step}")
        self.before.load_state_dict(state["before"])
        self.after.load_state_dict(state["after"])
        self.steps = int(state["steps"])
        self._road, self._env_step = None, None
