"""Mentors: simulated drivers of controlled skill and a real person at the controls.

All implement :class:`~pe_rlhf.mentors.base.Mentor`; ``make_mentor(name, seed)`` builds
one by name (``professional``, ``amateur``, ``adversarial``, ``human``).
"""

from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.driver import DriverParams, PrivilegedDriver

__all__ = ["DriverParams", "Mentor", "MentorDecision", "PrivilegedDriver"]
