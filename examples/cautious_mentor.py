"""A user's own mentor for the recipe: ``mentor.name=cautious_mentor:CautiousMentor``.

It drives like the IDM-MOBIL physics policy and takes over whenever the agent's action is more
than 0.5 away from its own in steering or throttle. Run it (from the repository root)::

    PYTHONPATH=examples python recipes/pe_rlhf/train.py profile=smoke mentor.name=cautious_mentor:CautiousMentor
"""

import numpy as np

from pe_rlhf.mentors import Mentor, MentorDecision
from pe_rlhf.physics import IDMMobilPolicy


class CautiousMentor(Mentor):
    name = "cautious"

    def __init__(self, tolerance: float = 0.5):
        self.tolerance, self.driver = tolerance, IDMMobilPolicy()

    def reset(self, env) -> None:
        self.driver.reset()

    def act(self, env) -> np.ndarray:
        return np.asarray(self.driver(env), dtype=np.float32)

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        mine = self.act(env)
        return MentorDecision(bool(np.abs(agent_action - mine).max() > self.tolerance), mine)
