"""``InterventionTransform``: a mentor (and, in PE-RLHF, physics + selector) takes over the agent's action.

Each step, before the simulator moves, the transform reads the agent's proposal
``action`` (``a_AV``), asks the mentor whether it takes over; during a takeover it asks the
physics policy for ``a_phy`` and the selector which of ``a_mentor`` / ``a_phy`` to execute
(PE-RLHF), or executes the mentor's action (HACO: no selector/physics). The executed action
replaces ``action`` only in the tensordict handed to the simulator, so the rollout keeps the
agent's proposal at the root, as TorchRL does for any action transform.

Writes under ``next`` (step outputs, float32 / bool with a trailing dim of 1 for flags):

===========================  =========================================================
``behavior_action`` (A,)     the executed action ``a_exec`` (``a_hybrid`` or ``a_AV``)
``intervention`` (1,)        the mentor held control this step
``intervention_start`` (1,)  first step of a takeover
``intervention_cost`` (1,)   ``1 - cos(a_AV, a_exec)`` at a start, else 0 (1 if a norm is ~0)
``mentor_action`` (A,)       the mentor's proposal (always present)
``physics_action`` (A,)      the physics proposal during a PE-RLHF takeover, else zeros (also in warm-up)
``mentor_selected`` (1,)     the mentor's action was executed in a takeover (always in HACO and in a
                             mentor-driven warm-up; never in a warm-up driven by ``warmup_driver``)
===========================  =========================================================

A non-finite agent proposal (a diverged actor) is never executed: its NaN/inf entries become 0 (straight,
coasting) for the mentor, the cost and the simulator, with a warning; the root ``action`` keeps it
as proposed.

Put it inside each worker's env factory (it drives the simulator of a single env). Mentor and physics
receive the simulator: the ``DrivingEnv`` of a driving env, or the gymnasium env's ``unwrapped`` of any
other TorchRL env over a gymnasium env (e.g. ``GymEnv("Pendulum-v1")``).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, Transform

from pe_rlhf.envs.torchrl_env import unwrap

OUT_KEYS = ("behavior_action", "intervention", "intervention_start", "intervention_cost", "mentor_action",
            "physics_action", "mentor_selected")
ZERO_NORM = 1e-6


def takeover_cost(agent_action: np.ndarray, executed_action: np.ndarray) -> float:
    """``1 - cos(a_AV, a_exec)``, in [0, 2]; 1 when either action is (near) zero or not finite (no
    direction to compare)."""
    na, ne = float(np.linalg.norm(agent_action)), float(np.linalg.norm(executed_action))
    if not (ZERO_NORM <= na < np.inf and ZERO_NORM <= ne < np.inf):  # also False for NaN
        return 1.0
    cos = float(np.dot(agent_action, executed_action)) / (na * ne)
    return float(1.0 - np.clip(cos, -1.0, 1.0))  # rounding can push |cos| a hair past 1


class InterventionTransform(Transform):
    """Mentor takeover with optional physics proposal and hybrid selection (see the module docstring).

    Args:
        mentor: any :class:`~pe_rlhf.mentors.base.Mentor`.
        selector: a :class:`~pe_rlhf.transforms.selector.HybridActionSelector` (PE-RLHF) or None (HACO).
        physics: a callable ``physics(env) -> action`` (e.g. ``IDMMobilPolicy()``), required with a selector.
        warmup_steps: for the first ``warmup_steps`` steps the mentor (or ``warmup_driver``) always drives
            and the selector is bypassed (the warm-up data that trains the Q-ensemble).
        warmup_driver: a policy ``driver(observation, env) -> action`` (observation float32 numpy ``(O,)``,
            action ``(A,)``; e.g. :class:`~pe_rlhf.evaluation.TorchRLPolicyAdapter` over a trained actor) that
            drives the warm-up instead of the mentor: the paper's *expert-policy warm-up*. The mentor is
            still asked every warm-up step (its proposal is written as ``mentor_action``); ``None``: the
            mentor drives (the *demonstration warm-up*).
    """

    def __init__(self, mentor, selector=None, physics=None, warmup_steps: int = 0, warmup_driver=None):
        super().__init__(in_keys=[], out_keys=list(OUT_KEYS))
        if (selector is None) != (physics is None):
            raise ValueError("InterventionTransform needs both selector and physics (PE-RLHF) or neither (HACO)")
        if warmup_steps < 0:
            raise ValueError(f"warmup_steps={warmup_steps} must be >= 0")
        self.mentor, self.selector, self.physics = mentor, selector, physics
        if warmup_driver is not None and not callable(warmup_driver):
            raise TypeError(f"warmup_driver must be a policy driver(observation, env) -> action, got "
                            f"{type(warmup_driver).__name__}")
        self.warmup_steps = int(warmup_steps)
        self.warmup_driver = warmup_driver
        self.total_steps = 0
        self._in_takeover = False
        self._previous_choice = False  # the selector's last choice (mentor?) in the current takeover
        self._pending: dict | None = None

    @property
    def driving_env(self):
        """The simulator handed to the mentor and physics: the ``DrivingEnv`` of a driving env; for any
        other base env (e.g. ``GymEnv("Pendulum-v1")``) the underlying gymnasium env's ``unwrapped``."""
        sim = unwrap(self.parent)
        gym_env = getattr(sim, "_env", None) if isinstance(sim, EnvBase) else None
        return getattr(gym_env, "unwrapped", gym_env) if gym_env is not None else sim

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._in_takeover = False
        self._pending = None
        self.mentor.reset(self.driving_env)
        if hasattr(self.warmup_driver, "reset"):
            self.warmup_driver.reset()
        # Defaults at reset, so reset and step outputs stack in a rollout.
        for key, spec in self.transform_observation_spec(Composite()).items():
            tensordict_reset.set(key, spec.zero())
        return tensordict_reset

    def _decide(self, observation: torch.Tensor, agent_action: np.ndarray) -> dict:
        env = self.driving_env
        warmup = self.total_steps < self.warmup_steps
        takeover, mentor_action = self.mentor(env, agent_action)
        mentor_action = np.asarray(mentor_action, dtype=np.float32)
        physics_action = np.zeros_like(mentor_action)
        mentor_selected = bool(takeover)
        executed = agent_action
        if warmup and self.warmup_driver is not None:
            executed = self._driver_action(observation, env, mentor_action.shape)
            takeover, mentor_selected = True, False
        elif warmup:
            takeover, executed, mentor_selected = True, mentor_action, True
        elif takeover:
            executed = mentor_action
            if self.selector is not None:
                physics_action = np.asarray(self.physics(env), dtype=np.float32)
                previous = self._previous_choice if self._in_takeover else None
                hybrid, chosen = self.selector.select(observation, torch.as_tensor(mentor_action),
                                                      torch.as_tensor(physics_action), previous, env=env)
                executed, mentor_selected = hybrid.numpy().astype(np.float32), bool(chosen.item())
        show = getattr(self.mentor, "show_control", None)
        if show is not None and takeover and not warmup:  # a person's window shows who drives now
            show("HUMAN" if mentor_selected else "PHYSICS")
        start = bool(takeover) and not self._in_takeover
        return {
            "behavior_action": executed,
            "intervention": bool(takeover),
            "intervention_start": start,
            "intervention_cost": takeover_cost(agent_action, executed) if start else 0.0,
            "mentor_action": mentor_action,
            "physics_action": physics_action,
            "mentor_selected": mentor_selected and bool(takeover),
        }

    def _driver_action(self, observation: torch.Tensor, env, shape: tuple[int, ...]) -> np.ndarray:
        obs = observation.detach().cpu().numpy().astype(np.float32)
        action = np.asarray(self.warmup_driver(obs, env), dtype=np.float32)
        if action.shape != shape or not np.isfinite(action).all():
            raise ValueError(f"warmup_driver returned {action.tolist()} (shape {action.shape}); expected a finite "
                             f"action of shape {shape}")
        return action

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        agent_action = tensordict.get("action")
        if agent_action.dim() != 1:
            raise ValueError(f"InterventionTransform drives one env; got action shape {tuple(agent_action.shape)}")
        a_av = agent_action.detach().cpu().numpy().astype(np.float32)
        if not np.isfinite(a_av).all():
            warnings.warn(f"InterventionTransform: the agent proposed {a_av.tolist()}; its non-finite entries "
                          "are executed as 0", RuntimeWarning, stacklevel=2)
            a_av = np.where(np.isfinite(a_av), a_av, np.float32(0.0))
        self._pending = self._decide(tensordict.get("observation"), a_av)
        tensordict.set("action", torch.as_tensor(self._pending["behavior_action"], dtype=agent_action.dtype))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        d = self._pending
        if d is None:
            raise RuntimeError("InterventionTransform._step without a decision: was the action set?")
        self._in_takeover = d["intervention"]
        self._previous_choice = d["mentor_selected"]
        self.total_steps += 1
        for key in ("behavior_action", "mentor_action", "physics_action"):
            next_tensordict.set(key, torch.as_tensor(d[key], dtype=torch.float32))
        for key in ("intervention", "intervention_start", "mentor_selected"):
            next_tensordict.set(key, torch.tensor([d[key]], dtype=torch.bool))
        next_tensordict.set("intervention_cost", torch.tensor([d["intervention_cost"]], dtype=torch.float32))
        self._pending = None
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        action_shape = self.parent.full_action_spec["action"].shape if self.parent is not None else (2,)
        for key in ("behavior_action", "mentor_action", "physics_action"):
            observation_spec[key] = Unbounded(action_shape, dtype=torch.float32)
        for key in ("intervention", "intervention_start", "mentor_selected"):
            observation_spec[key] = Unbounded((1,), dtype=torch.bool)
        observation_spec["intervention_cost"] = Unbounded((1,), dtype=torch.float32)
        return observation_spec

    def state_dict_extra(self) -> dict:
        """Counters and mentor state for checkpoints."""
        return {"total_steps": self.total_steps, "mentor": self.mentor.state_dict()}
