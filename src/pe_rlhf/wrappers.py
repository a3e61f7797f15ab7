"""The takeover machinery as a gymnasium wrapper, and the TorchRL reader of what it reports.

:class:`InterventionWrapper` runs :class:`~pe_rlhf.transforms.takeover_core.TakeoverCore`, the decision
logic of :class:`~pe_rlhf.transforms.InterventionTransform`, around any gymnasium env: ``step(action)``
executes the agent's action or the takeover's (the mentor's, or the physics policy's where the selector
picks it) and reports it in ``info``:

========================  ========================  ===============================================
``info`` key              TorchRL key               value
========================  ========================  ===============================================
``is_intervention``       (gym-hil's flag)          bool: the mentor held control this step
``teleop_action``         ``behavior_action``       float32 ``(A,)``: the executed action (the
                                                    takeover's while ``is_intervention``; gym-hil's)
``intervention``          ``intervention``          bool, as ``is_intervention``
``intervention_start``    ``intervention_start``    bool: first step of a takeover
``intervention_cost``     ``intervention_cost``     float: ``1 - cos(a_AV, a_exec)`` at a start, else 0
``mentor_action``         ``mentor_action``         float32 ``(A,)``: the mentor's proposal (every step)
``physics_action``        ``physics_action``        float32 ``(A,)``, only with physics: its proposal
                                                    in a takeover, else zeros (TorchRL: zeros without)
``mentor_selected``       ``mentor_selected``       bool: the mentor's action ran in a takeover
``agent_action``          (the root ``action``)     float32 ``(A,)``: the agent's proposal as given
========================  ========================  ===============================================

:class:`InfoToTakeoverKeys` is the TorchRL side: an info-dict reader for ``GymWrapper``/``GymEnv`` that
writes those keys as :class:`~pe_rlhf.transforms.InterventionTransform` does (same names, dtypes, shapes;
zeros/False at reset), so a TorchRL pipeline over a wrapped gymnasium env gets the transform's tensordict.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs.gym_like import BaseInfoDictReader

from pe_rlhf.transforms.keys import (BEHAVIOR_ACTION, INTERVENTION, INTERVENTION_COST, INTERVENTION_START,
                                     MENTOR_ACTION, MENTOR_SELECTED, OUT_KEYS, PHYSICS_ACTION)
from pe_rlhf.transforms.takeover_core import TakeoverCore, TakeoverStep, takeover_specs, takeover_tensors
from pe_rlhf.transforms.shield import DEFAULT_THRESHOLD, ShieldCore
from pe_rlhf.transforms.keys import (PHYSICS_TIME_TO_FAILURE, POLICY_TIME_TO_FAILURE, SHIELD_OVERRIDE,
                                     SHIELDED_ACTION)

# TorchRL key <- info key (the rest of OUT_KEYS keep their names).
INFO_KEY = {key: key for key in OUT_KEYS} | {BEHAVIOR_ACTION: "teleop_action"}


class InterventionWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """A mentor (and, in PE-RLHF, physics + selector) takes over the agent's action in a gymnasium env.

    The same arguments and decisions as :class:`~pe_rlhf.transforms.InterventionTransform` (``mentor``,
    ``physics``, ``selector``, ``warmup_steps``, ``warmup_driver``, ``warmup_selection``); the mentor
    and physics get the
    wrapped env's ``unwrapped`` (e.g. ``DrivingEnv``, ``PendulumEnv``). Actions are 1-D; the selector and
    a warm-up driver see the last observation returned. ``info`` keys: the module docstring.

    The arguments are recorded in ``env.spec`` as gymnasium's wrappers do, so ``env.spec.make()`` rebuilds
    the stack (the rebuilt wrapper shares these mentor, physics and selector objects).
    """

    def __init__(self, env: gym.Env, mentor, physics=None, selector=None, warmup_steps: int = 0,
                 warmup_driver=None, warmup_selection: bool = False):
        # no deepcopy: the rebuilt wrapper shares these objects (a person's window cannot be copied)
        gym.utils.RecordConstructorArgs.__init__(self, _disable_deepcopy=True, mentor=mentor, physics=physics,
                                                 selector=selector,
                                                 warmup_steps=warmup_steps, warmup_driver=warmup_driver,
                                                 warmup_selection=warmup_selection)
        gym.Wrapper.__init__(self, env)
        self.core = TakeoverCore(mentor, selector, physics, warmup_steps, warmup_driver,
                                 owner="InterventionWrapper", warmup_selection=warmup_selection)
        self._observation = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """gymnasium's reset; a ``seed`` also reseeds the mentor (``Mentor.reseed``) and starts the selector's veto
        count afresh, so that the same seed and actions give the same episode (gymnasium's ``check_env``)."""
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self._reseed(int(seed))
        self.core.reset(self.unwrapped)
        self._observation = obs
        return obs, info

    def _reseed(self, seed: int) -> None:
        core = self.core
        if hasattr(core.mentor, "reseed"):
            core.mentor.reseed(seed)
        if hasattr(core.warmup_driver, "reseed"):
            core.warmup_driver.reseed(seed)
        if hasattr(core.physics, "reset"):
            core.physics.reset()  # no lane plan carried over
        core.load_state_dict({})  # no takeover in progress, no previous choice, the selector's veto count afresh

    def step(self, action):
        if self._observation is None:
            raise RuntimeError("InterventionWrapper: call reset() before step()")
        d = self.core.decide(self.unwrapped, self._observation, action)
        dtype = getattr(self.action_space, "dtype", None)
        executed = d.behavior_action.astype(np.float32 if dtype is None else dtype)
        obs, reward, terminated, truncated, info = self.env.step(executed)
        self.core.commit()
        self._observation = obs
        return obs, reward, terminated, truncated, {**info, **self._info(d, action)}

    def _info(self, d: TakeoverStep, action) -> dict:
        """The ``info`` entries of decision ``d`` for the proposal ``action``."""
        info = {
            "is_intervention": d.intervention,
            "teleop_action": d.behavior_action.copy(),
            INTERVENTION: d.intervention,
            INTERVENTION_START: d.intervention_start,
            INTERVENTION_COST: d.intervention_cost,
            MENTOR_ACTION: d.mentor_action.copy(),
            MENTOR_SELECTED: d.mentor_selected,
            "agent_action": np.array(action, dtype=np.float32),
        }
        if self.core.physics is not None:
            info[PHYSICS_ACTION] = d.physics_action.copy()
        return info

    @property
    def total_steps(self) -> int:
        """Steps executed through the wrapper (the warm-up counts them)."""
        return self.core.total_steps


class InfoToTakeoverKeys(BaseInfoDictReader):
    """Reads :class:`InterventionWrapper`'s ``info`` into :class:`~pe_rlhf.transforms.InterventionTransform`'s keys.

    ``GymWrapper(InterventionWrapper(env, mentor)).set_info_dict_reader(InfoToTakeoverKeys(env.action_space.shape))``
    writes ``behavior_action``, ``intervention``, ``intervention_start``, ``intervention_cost``,
    ``mentor_action``, ``physics_action`` and ``mentor_selected`` (mapping: the module docstring) with the
    transform's specs; a key the info lacks (a reset, or ``physics_action`` without physics) is zeros.
    The root ``action`` keeps the agent's proposal, as under the transform. One env (unbatched info).
    """

    def __init__(self, action_shape=(2,)):
        self._specs = Composite(takeover_specs(torch.Size(action_shape)), shape=[])

    def __call__(self, info_dict: dict, tensordict: TensorDictBase) -> TensorDictBase:
        specs = self._specs
        values = {key: info_dict[INFO_KEY[key]] if INFO_KEY[key] in info_dict else specs[key].zero()
                  for key in OUT_KEYS}
        tensordict.update(takeover_tensors(values))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._specs


__all__ = ["INFO_KEY", "InfoToTakeoverKeys", "InterventionWrapper"]


class SafetyShieldWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The runtime shield of :class:`~pe_rlhf.transforms.SafetyShield` around a gymnasium driving env.

    The same arguments and decisions (:class:`~pe_rlhf.transforms.ShieldCore`: the policy's action is replaced
    by physics' where it is forecast to fail more than ``threshold`` seconds sooner, until it no longer is);
    physics and the forecast read the wrapped env's ``unwrapped`` (a ``DrivingEnv``). ``info`` gets the
    transform's keys: ``shield_override`` (bool), ``shielded_action`` (float32 ``(2,)``, executed),
    ``policy_time_to_failure`` and ``physics_time_to_failure`` (float, seconds), plus ``shield_latency``
    (seconds the decision took). Works with any policy that calls ``env.step(action)`` (an SB3 model's
    ``predict``: ``examples/sb3_shield.py``).
    """

    def __init__(self, env: gym.Env, threshold: float = DEFAULT_THRESHOLD, physics=None, selector=None,
                 persistence: str = "latch"):
        gym.utils.RecordConstructorArgs.__init__(self, threshold=threshold, physics=physics, selector=selector,
                                                 persistence=persistence)
        gym.Wrapper.__init__(self, env)
        self.core = ShieldCore(threshold, physics, selector, persistence)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.core.reset(self.unwrapped)
        return obs, info

    def step(self, action):
        d = self.core.decide(self.unwrapped, action)
        executed = d.action if d.override else np.asarray(action, dtype=np.float32).reshape(d.action.shape)
        obs, reward, terminated, truncated, info = self.env.step(executed)
        return obs, reward, terminated, truncated, {
            **info, SHIELD_OVERRIDE: d.override, SHIELDED_ACTION: np.array(executed, dtype=np.float32),
            POLICY_TIME_TO_FAILURE: d.policy_time_to_failure, PHYSICS_TIME_TO_FAILURE: d.physics_time_to_failure,
            "shield_latency": d.latency}


__all__ += ["SafetyShieldWrapper"]
