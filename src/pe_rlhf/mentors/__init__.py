"""Mentors: simulated drivers of controlled skill and a real person at the controls.

All implement :class:`~pe_rlhf.mentors.base.Mentor`; ``make_mentor(name, seed)`` builds
one by name (``professional``, ``amateur``, ``adversarial``/``bad``, ``collapsing``, ``human``; the persistent
adversaries of :mod:`pe_rlhf.mentors.adversaries` are test and benchmark drivers).
"""

from pe_rlhf.mentors.adversaries import ADVERSARY_NAMES, PersistentAdversary, make_adversary
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.collapsing import CollapsingMentor
from pe_rlhf.mentors.driver import DriverParams, PrivilegedDriver
from pe_rlhf.mentors.registry import MENTOR_NAMES, MentorPolicy, make_mentor
from pe_rlhf.mentors.simulated import PRESETS, SimulatedMentor, SkillProfile
from pe_rlhf.mentors.takeover import TakeoverRule



def __getattr__(name: str):
    if name == "HumanMentor":  # lazy: importing it opens pygame's display machinery
        from pe_rlhf.mentors.human import HumanMentor

        return HumanMentor
    raise AttributeError(f"module 'pe_rlhf.mentors' has no attribute {name!r}")


__all__ = [
    "ADVERSARY_NAMES",
    "PersistentAdversary",
    "make_adversary",
    "CollapsingMentor",
    "HumanMentor",
    "MENTOR_NAMES",
    "PRESETS",
    "DriverParams",
    "Mentor",
    "MentorDecision",
    "MentorPolicy",
    "PrivilegedDriver",
    "SimulatedMentor",
    "SkillProfile",
    "TakeoverRule",
    "make_mentor",
]
