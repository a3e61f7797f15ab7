"""The world a recipe config describes, as every method builds it: the observation width and the mentor.

Any recipe config with a ``seed``, an ``env`` group (:func:`~pe_rlhf.runtime.config.driving_config`) and a ``mentor``
group (``name``, ``kwargs``) will do: the proxy-Q recipes' (:mod:`pe_rlhf.algorithms.proxy_q.builders` builds the rest
of their env, collector and learner) and the baselines'.
"""

from __future__ import annotations

import importlib

from pe_rlhf.mentors import Mentor, make_mentor


def obs_dim(cfg) -> int:
    """The observation size of ``cfg.env``'s world (the networks' input width)."""
    from pe_rlhf.envs.observation import observation_size
    from pe_rlhf.runtime.config import driving_config

    world = driving_config(cfg)
    return observation_size(world.lidar_beams, world.lane_features)


def build_mentor(cfg, worker_index: int = 0) -> Mentor:
    """A mentor by preset name (seeded ``seed + worker_index``: the run's seed), or a user's class given as
    ``package.module:Name``."""
    name = str(cfg.mentor.name)
    if ":" in name:
        module_name, _, attr = name.partition(":")
        mentor = getattr(importlib.import_module(module_name), attr)()
        if not isinstance(mentor, Mentor):
            raise TypeError(f"mentor.name={name!r} built a {type(mentor).__name__}, not a pe_rlhf Mentor")
        return mentor
    kwargs = dict(cfg.mentor.get("kwargs") or {})
    if name == "human" and float(cfg.collector.realtime_hz) > 0:
        # RealtimePacing holds the step rate; the window's own frame limiter at twice that rate never
        # waits between steps (two clocks would fight) but still throttles the redraws while paused.
        kwargs.setdefault("fps", 2.0 * float(cfg.collector.realtime_hz))
    return make_mentor(name, int(cfg.seed) + int(worker_index), **kwargs)


__all__ = ["build_mentor", "obs_dim"]
