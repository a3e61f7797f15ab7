"""Mentors by name, and mentors as evaluation policies.

``make_mentor(name, seed, **overrides)`` builds ``professional``, ``amateur``,
``adversarial`` (alias ``bad``) simulated mentors, with :class:`SkillProfile` fields as
overrides, ``collapsing`` (:class:`~pe_rlhf.mentors.collapsing.CollapsingMentor`: one
preset, then another from a given step; overrides ``switch_step``, ``before``, ``after``), or
``human`` (:class:`pe_rlhf.mentors.human.HumanMentor`, overrides passed to its constructor,
seed unused), or a persistent adversary (test and benchmark drivers, :mod:`pe_rlhf.mentors.adversaries`:
``seek-collision``, ``never-brake``, ``drift-off-road``, ``uniform-random``). Importing this module registers the simulated presets
with :func:`pe_rlhf.evaluation.register_policy` so ``pe-rlhf evaluate --policy
professional`` drives the mentor alone.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pe_rlhf.evaluation.policies import POLICY_FACTORIES, register_policy
from pe_rlhf.mentors.adversaries import ADVERSARY_NAMES, make_adversary
from pe_rlhf.mentors.base import Mentor
from pe_rlhf.mentors.simulated import ALIASES, PRESETS, SimulatedMentor, SkillProfile, preset

MENTOR_NAMES = tuple(sorted(PRESETS)) + tuple(sorted(ALIASES)) + ("collapsing", "human") + ADVERSARY_NAMES


def make_mentor(name: str, seed: int = 0, **overrides) -> Mentor:
    """A fresh mentor by name.

    In: ``name`` (one of :data:`MENTOR_NAMES`), ``seed`` (the simulated mentor's RNG),
    ``overrides`` (SkillProfile fields, e.g. ``action_noise=0.1``). Unknown names or
    fields raise ``ValueError`` listing the allowed ones.
    """
    if name == "human":
        try:
            from pe_rlhf.mentors.human import HumanMentor
        except ImportError as e:
            raise ValueError(f"mentor 'human' needs pe_rlhf.mentors.human.HumanMentor (pygame), "
                             f"which failed to import: {e}") from e
        return HumanMentor(**overrides)
    if name == "collapsing":
        from pe_rlhf.mentors.collapsing import COLLAPSING_KWARGS, CollapsingMentor

        unknown = sorted(set(overrides) - set(COLLAPSING_KWARGS))
        if unknown:
            raise ValueError(f"unknown CollapsingMentor argument(s) {unknown}; known: {list(COLLAPSING_KWARGS)}")
        return CollapsingMentor(seed=seed, **overrides)
    if name in ADVERSARY_NAMES:  # test and benchmark drivers (pe_rlhf.mentors.adversaries)
        if overrides:
            raise ValueError(f"adversary {name!r} takes no overrides, got {sorted(overrides)}")
        return make_adversary(name, seed)
    if ALIASES.get(name, name) not in PRESETS:
        raise ValueError(f"unknown mentor {name!r}; allowed: {list(MENTOR_NAMES)}")
    known = {f.name for f in dataclasses.fields(SkillProfile)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"unknown SkillProfile field(s) {unknown}; known: {sorted(known)}")
    profile = dataclasses.replace(preset(name), **overrides)
    return SimulatedMentor(profile, seed=seed, name=ALIASES.get(name, name))


class MentorPolicy:
    """A mentor driving alone, as an evaluation policy: ``policy(obs, env) -> mentor.act(env)``.

    Calls ``mentor.reset(env)`` at each episode start, detected by a new ``env.road``
    (every ``env.reset`` builds one) or after ``reset()``. ``obs`` is ignored.
    """

    def __init__(self, mentor: Mentor):
        self.mentor = mentor
        self._road = None

    def reset(self) -> None:
        self._road = None

    def __call__(self, obs, env) -> np.ndarray:
        env = getattr(env, "unwrapped", env)
        if env.road is not self._road:
            self._road = env.road
            self.mentor.reset(env)
        return np.asarray(self.mentor.act(env), dtype=np.float32).reshape(2)


def _register() -> None:
    for name in sorted(PRESETS):
        if name not in POLICY_FACTORIES:
            register_policy(name, lambda seed, name=name: MentorPolicy(make_mentor(name, seed)))
    for name in ADVERSARY_NAMES:
        if name not in POLICY_FACTORIES:
            register_policy(name, lambda seed, name=name: MentorPolicy(make_adversary(name, seed)))


_register()

__all__ = ["MENTOR_NAMES", "MentorPolicy", "make_mentor"]
