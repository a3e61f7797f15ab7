"""``InterventionTransform``: a mentor (and, in PE-RLHF, physics + selector) takes over the agent's action.

Each step, before the simulator moves, the transform reads the agent's proposal
``action`` (``a_AV``), asks the mentor whether it takes over; during a takeover it asks the
physics policy for ``a_phy`` and the selector which of ``a_mentor`` / ``a_phy`` to execute
(PE-RLHF), or executes the mentor's action (HACO: no selector/physics). The executed action
replaces ``action`` only in the tensordict handed to the simulator, so the rollout keeps the
agent's proposal at the root, as TorchRL does for any action transform.

Reads the root ``action`` and ``observation`` (``in_keys``); writes under ``next`` (step outputs, float32 /
bool with a trailing dim of 1 for flags; ``out_keys`` renames them, in this order, defaults in
:mod:`pe_rlhf.transforms.keys`):

===========================  =========================================================
``behavior_action`` (A,)     the executed action ``a_exec`` (``a_hybrid`` or ``a_AV``)
``intervention`` (1,)        the mentor held control this step
``intervention_start`` (1,)  first step of a takeover
``intervention_cost`` (1,)   ``1 - cos(a_AV, a_exec)`` at a start, else 0 (1 if a norm is ~0)
``mentor_action`` (A,)       the mentor's proposal (always present)
``physics_action`` (A,)      the physics proposal during a PE-RLHF takeover, else zeros (in warm-up too,
                             unless ``warmup_selection``)
``mentor_selected`` (1,)     the mentor's action was executed in a takeover (always in HACO and in a
                             mentor-driven warm-up without ``warmup_selection``; never in a warm-up
                             driven by ``warmup_driver``)
===========================  =========================================================

A non-finite agent proposal (a diverged actor) is never executed: its NaN/inf entries become 0 (straight,
coasting) for the mentor, the cost and the simulator, with a warning; the root ``action`` keeps it
as proposed.

**Selection as a transform of its own.** Given ``physics`` and no selector, the transform only *proposes*:
during a takeover it writes ``mentor_action``, ``physics_action`` and ``intervention`` (True: a step to judge;
False in the warm-up unless ``warmup_selection``) into the tensordict on its way to the simulator, and a
:class:`~pe_rlhf.transforms.HybridSelectionTransform` nearer the simulator chooses; the step outputs then
follow what it executed (``behavior_action``, ``mentor_selected``, the takeover cost)::

    env = TransformedEnv(base, Compose(HybridSelectionTransform(selector),
                                       InterventionTransform(mentor, physics=IDMMobilPolicy())))

TorchRL runs inverse transforms from the last in a ``Compose`` to the first, so the selection, which follows
the proposals in the action's path, sits *before* the transform that writes them.

Put it inside each worker's env factory (it drives the simulator of a single env). Mentor and physics
receive the simulator: the ``DrivingEnv`` of a driving env, or the gymnasium env's ``unwrapped`` of any
other TorchRL env over a gymnasium env (e.g. ``GymEnv("Pendulum-v1")``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs import EnvBase, Transform

from pe_rlhf.envs.torchrl_env import unwrap
from pe_rlhf.transforms.keys import INTERVENTION, MENTOR_ACTION, MENTOR_SELECTED, PHYSICS_ACTION
from pe_rlhf.transforms.takeover_core import (OUT_KEYS, ZERO_NORM, TakeoverCore, takeover_cost, takeover_specs,
                                              takeover_tensors)


def simulator_of(env):
    """The simulator a transform of ``env`` hands to mentors, physics and forecasts: the ``DrivingEnv`` of a
    driving env; for any other TorchRL env over a gymnasium env the gymnasium env's ``unwrapped``."""
    sim = unwrap(env)
    gym_env = getattr(sim, "_env", None) if isinstance(sim, EnvBase) else None
    return getattr(gym_env, "unwrapped", gym_env) if gym_env is not None else sim


class InterventionTransform(Transform):
    """Mentor takeover with optional physics proposal and hybrid selection (see the module docstring).

    The decision itself is :class:`~pe_rlhf.transforms.takeover_core.TakeoverCore`'s (``core``), shared
    with the gymnasium face :class:`~pe_rlhf.wrappers.InterventionWrapper`.

    Args:
        mentor: any :class:`~pe_rlhf.mentors.base.Mentor`.
        selector: a :class:`~pe_rlhf.transforms.selector.HybridActionSelector` (PE-RLHF) or None (HACO, or
            the selection left to a :class:`~pe_rlhf.transforms.HybridSelectionTransform`: module docstring).
        physics: a callable ``physics(env) -> action`` (e.g. ``IDMMobilPolicy()``), required with a selector;
            without one, the transform proposes physics' action to a selection transform.
        warmup_steps: for the first ``warmup_steps`` steps the mentor (or ``warmup_driver``) always drives
            and the selector is bypassed (the warm-up data that trains the Q-ensemble).
        in_keys: ``[action_key, observation_key]``: where the agent's proposal is (and the executed action
            goes: the env's action key) and the observation the selector and a warm-up driver read.
        out_keys: the seven step outputs' names, in the order of :data:`~pe_rlhf.transforms.keys.OUT_KEYS`.
        warmup_selection: the selector judges the mentor's warm-up actions too (physics proposes every
            warm-up step): for a value source that needs no fit (the physics forecast, a frozen expert),
            so a bad mentor's warm-up is as safe as its takeovers. Needs a selector and no ``warmup_driver``.
        warmup_driver: a policy ``driver(observation, env) -> action`` (observation float32 numpy ``(O,)``,
            action ``(A,)``; e.g. :class:`~pe_rlhf.evaluation.TorchRLPolicyAdapter` over a trained actor) that
            drives the warm-up instead of the mentor: the paper's *expert-policy warm-up*. The mentor is
            still asked every warm-up step (its proposal is written as ``mentor_action``); ``None``: the
            mentor drives (the *demonstration warm-up*).
    """

    def __init__(self, mentor, selector=None, physics=None, warmup_steps: int = 0, warmup_driver=None,
                 warmup_selection: bool = False, *, in_keys=("action", "observation"), out_keys=OUT_KEYS):
        in_keys, out_keys = list(in_keys), list(out_keys)
        if len(in_keys) != 2 or len(out_keys) != len(OUT_KEYS) or len(set(map(str, out_keys))) != len(OUT_KEYS):
            raise ValueError(f"InterventionTransform: in_keys are [action, observation] (got {in_keys}); out_keys are "
                             f"{len(OUT_KEYS)} distinct names in the order {list(OUT_KEYS)} (got {out_keys})")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.action_key, self.observation_key = in_keys
        self._renamed = dict(zip(OUT_KEYS, out_keys))
        self.core = TakeoverCore(mentor, selector, physics, warmup_steps, warmup_driver,
                                 owner="InterventionTransform", warmup_selection=warmup_selection,
                                 propose_physics=selector is None and physics is not None)
        # The same objects as the core's; attributes of the module as before (a selector is a submodule).
        self.mentor, self.selector, self.physics = mentor, selector, physics

    @property
    def warmup_steps(self) -> int:
        return self.core.warmup_steps

    @property
    def warmup_driver(self):
        return self.core.warmup_driver

    @property
    def total_steps(self) -> int:
        """Steps executed over the transform's life (the warm-up counts them); set on a resumed run."""
        return self.core.total_steps

    @total_steps.setter
    def total_steps(self, value: int) -> None:
        self.core.total_steps = int(value)

    @property
    def driving_env(self):
        """The simulator handed to the mentor and physics: the ``DrivingEnv`` of a driving env; for any
        other base env (e.g. ``GymEnv("Pendulum-v1")``) the underlying gymnasium env's ``unwrapped``."""
        return simulator_of(self.parent)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self.core.reset(self.driving_env)
        # Defaults at reset, so reset and step outputs stack in a rollout.
        for key, spec in self.transform_observation_spec(Composite()).items():
            tensordict_reset.set(key, spec.zero())
        return tensordict_reset

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # nothing to do outside an env step (the decision needs the simulator)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        agent_action = tensordict.get(self.action_key)
        d = self.core.decide(self.driving_env, tensordict.get(self.observation_key),
                             agent_action.detach().cpu().numpy())
        tensordict.set(self.action_key, torch.as_tensor(d.behavior_action, dtype=agent_action.dtype))
        if self.core.propose_physics:  # proposals for a HybridSelectionTransform nearer the simulator
            tensordict.set(self._renamed[MENTOR_ACTION], torch.as_tensor(d.mentor_action, dtype=agent_action.dtype))
            tensordict.set(self._renamed[PHYSICS_ACTION], torch.as_tensor(d.physics_action, dtype=agent_action.dtype))
            tensordict.set(self._renamed[INTERVENTION], torch.tensor([d.judged]))
            # The root carries the last step's choice (an observation); a selection nearer the simulator
            # writes this step's. Dropped here, so a selection placed on the wrong side is caught in _step.
            if self._renamed[MENTOR_SELECTED] in tensordict.keys():
                del tensordict[self._renamed[MENTOR_SELECTED]]
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        pending = self.core.pending
        if pending is not None and pending.judged:  # ``tensordict`` is what the simulator received
            chosen = tensordict.get(self._renamed[MENTOR_SELECTED], None)
            if chosen is None:
                raise RuntimeError("InterventionTransform(physics=..., selector=None) proposes physics' action to a "
                                   "HybridSelectionTransform, and none judged this step: put one before it in the "
                                   "Compose (nearer the simulator), or pass a selector")
            self.core.settle(tensordict.get(self.action_key).detach().cpu().numpy(), bool(chosen.any()))
        next_tensordict.update({self._renamed[k]: v for k, v in takeover_tensors(self.core.commit()).items()})
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        action_shape = self.parent.full_action_spec[self.action_key].shape if self.parent is not None else (2,)
        for key, spec in takeover_specs(action_shape).items():
            observation_spec[self._renamed[key]] = spec
        return observation_spec

    def state_dict_extra(self) -> dict:
        """Counters and mentor state for checkpoints."""
        return {"total_steps": self.total_steps, "mentor": self.mentor.state_dict()}


__all__ = ["OUT_KEYS", "ZERO_NORM", "InterventionTransform", "simulator_of", "takeover_cost"]
