"""``TakeoverCore``: one step of the takeover decision, in plain Python, for every face that drives a simulator.

:class:`~pe_rlhf.transforms.InterventionTransform` (TorchRL) and :class:`~pe_rlhf.wrappers.InterventionWrapper`
(gymnasium) both call it, so a takeover is decided by one implementation: per step, ``decide`` (before the
simulator moves) asks the mentor, during a PE-RLHF takeover the physics policy and the selector, handles the
warm-up, the takeover start and the cosine takeover cost; ``commit`` (after the simulator moved) advances the
takeover state and the step counter. A decision is a :class:`TakeoverStep`, whose fields are named as the
tensordict keys the transform writes (:data:`OUT_KEYS`, specs from :func:`takeover_specs`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
import torch
from torchrl.data import Unbounded

from pe_rlhf.transforms.keys import ACTION_KEYS, COST_KEY, FLAG_KEYS, OUT_KEYS  # noqa: F401 (re-exported)

ZERO_NORM = 1e-6


def takeover_cost(agent_action: np.ndarray, executed_action: np.ndarray) -> float:
    """``1 - cos(a_AV, a_exec)``, in [0, 2]; 1 when either action is (near) zero or not finite (no
    direction to compare)."""
    na, ne = float(np.linalg.norm(agent_action)), float(np.linalg.norm(executed_action))
    if not (ZERO_NORM <= na < np.inf and ZERO_NORM <= ne < np.inf):  # also False for NaN
        return 1.0
    cos = float(np.dot(agent_action, executed_action)) / (na * ne)
    return float(1.0 - np.clip(cos, -1.0, 1.0))  # rounding can push |cos| a hair past 1


def takeover_specs(action_shape) -> dict:
    """The spec of each of :data:`OUT_KEYS` for actions of shape ``action_shape``."""
    specs = {key: Unbounded(action_shape, dtype=torch.float32) for key in ACTION_KEYS}
    specs.update({key: Unbounded((1,), dtype=torch.bool) for key in FLAG_KEYS})
    specs[COST_KEY] = Unbounded((1,), dtype=torch.float32)
    return specs


def takeover_tensors(values) -> dict[str, torch.Tensor]:
    """:data:`OUT_KEYS` of a mapping (or a :class:`TakeoverStep`) as the tensors of :func:`takeover_specs`."""
    get = values.get if isinstance(values, dict) else lambda key: getattr(values, key)
    out = {key: torch.as_tensor(get(key), dtype=torch.float32) for key in ACTION_KEYS}
    out.update({key: torch.tensor([bool(get(key))], dtype=torch.bool) for key in FLAG_KEYS})
    out[COST_KEY] = torch.tensor([float(get(COST_KEY))], dtype=torch.float32)
    return out


@dataclass(frozen=True)
class TakeoverStep:
    """One step's decision; fields but ``agent_action`` are the transform's keys (module docstring of
    :mod:`pe_rlhf.transforms.intervention`). Actions are float32 ``(A,)``."""

    agent_action: np.ndarray  # the proposal the mentor and the cost saw (non-finite entries as 0)
    behavior_action: np.ndarray  # executed
    intervention: bool
    intervention_start: bool
    intervention_cost: float
    mentor_action: np.ndarray
    physics_action: np.ndarray  # zeros outside a PE-RLHF takeover
    mentor_selected: bool
    judged: bool = False  # proposed to a selection downstream (``propose_physics``), settled by ``settle``


class TakeoverCore:
    """The takeover state machine of one env (see the module docstring); arguments as
    :class:`~pe_rlhf.transforms.InterventionTransform`'s.

    ``owner`` names the face in errors and warnings. ``env`` arguments are the simulator handed to the
    mentor, the physics policy and the selector (a ``DrivingEnv``, or a gymnasium env's ``unwrapped``).

    ``propose_physics`` (physics and no selector): during a takeover (and every warm-up step with
    ``warmup_selection``) physics proposes its action and the decision is marked ``judged``; the mentor's action
    stands until :meth:`settle` is told what a selection outside the core executed
    (:class:`~pe_rlhf.transforms.HybridSelectionTransform`).
    """

    def __init__(self, mentor, selector=None, physics=None, warmup_steps: int = 0, warmup_driver=None,
                 owner: str = "TakeoverCore", warmup_selection: bool = False, propose_physics: bool = False):
        if propose_physics and (physics is None or selector is not None):
            raise ValueError(f"{owner}: propose_physics needs physics and no selector (a selection transform "
                             "judges the proposals)")
        if not propose_physics and (selector is None) != (physics is None):
            raise ValueError(f"{owner} needs both selector and physics (PE-RLHF) or neither (HACO)")
        if warmup_steps < 0:
            raise ValueError(f"warmup_steps={warmup_steps} must be >= 0")
        if warmup_driver is not None and not callable(warmup_driver):
            raise TypeError(f"warmup_driver must be a policy driver(observation, env) -> action, got "
                            f"{type(warmup_driver).__name__}")
        self.mentor, self.selector, self.physics = mentor, selector, physics
        self.propose_physics = bool(propose_physics)
        if warmup_selection and ((selector is None and not propose_physics) or warmup_driver is not None):
            raise ValueError(f"{owner}: warmup_selection needs a selector and a mentor-driven warm-up "
                             "(no warmup_driver)")
        self.warmup_steps = int(warmup_steps)
        self.warmup_driver = warmup_driver
        self.warmup_selection = bool(warmup_selection)
        self.owner = owner
        self.total_steps = 0
        self._in_takeover = False
        self._previous_choice = False  # the selector's last choice (mentor?) in the current takeover
        self.pending: TakeoverStep | None = None

    def reset(self, env) -> None:
        """Episode start (after the simulator's reset): no takeover carries over."""
        self._in_takeover = False
        self.pending = None
        self.mentor.reset(env)
        if hasattr(self.warmup_driver, "reset"):
            self.warmup_driver.reset()

    def state_dict(self, env=None) -> dict:
        """The takeover in progress between two steps, as JSON data: ``in_takeover``, ``previous_choice`` (the
        selector's last choice in it), ``selector`` (its veto count: ``HybridActionSelector.streak_state``) and
        ``physics`` (its lane plan, when it has a ``state_dict``; ``env``: the simulator, whose episode the plan
        must belong to). The mentor's state and ``total_steps`` are saved apart (checkpoint ``mentor``,
        ``transform_steps``)."""
        streak = getattr(self.selector, "streak_state", None)
        physics = getattr(self.physics, "state_dict", None)
        return {"in_takeover": self._in_takeover, "previous_choice": self._previous_choice,
                "selector": streak() if streak is not None else None,
                "physics": physics(env) if physics is not None else None}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (keys it lacks keep their fresh value); no decision is pending after it."""
        self._in_takeover = bool(state.get("in_takeover", False))
        self._previous_choice = bool(state.get("previous_choice", False))
        self.pending = None
        if hasattr(self.selector, "load_streak_state"):
            self.selector.load_streak_state(state.get("selector"))
        if state.get("physics") is not None and hasattr(self.physics, "load_state_dict"):
            self.physics.load_state_dict(state["physics"])

    def decide(self, env, observation, agent_action) -> TakeoverStep:
        """This step's decision for the agent's proposal ``agent_action`` ``(A,)`` at ``observation`` ``(O,)``
        (tensor or array); kept as ``pending`` until :meth:`commit`."""
        a_av = self._sanitized(agent_action)
        warmup = self.total_steps < self.warmup_steps
        takeover, mentor_action = self.mentor(env, a_av)
        mentor_action = np.asarray(mentor_action, dtype=np.float32)
        physics_action = np.zeros_like(mentor_action)
        mentor_selected = bool(takeover)
        executed = a_av
        judged = False
        if warmup and self.warmup_driver is not None:
            executed = self._driver_action(observation, env, mentor_action.shape)
            takeover, mentor_selected = True, False
        elif warmup:
            takeover, executed, mentor_selected = True, mentor_action, True
            if self.warmup_selection:  # a value source that needs no fit judges the warm-up too
                physics_action = np.asarray(self.physics(env), dtype=np.float32)
                judged = self.propose_physics
                if not judged:
                    executed, mentor_selected = self._select(env, observation, mentor_action, physics_action)
        elif takeover:
            executed = mentor_action
            if self.selector is not None or self.propose_physics:
                physics_action = np.asarray(self.physics(env), dtype=np.float32)
                judged = self.propose_physics
                if not judged:
                    executed, mentor_selected = self._select(env, observation, mentor_action, physics_action)
        if takeover and not warmup and not judged:
            self._show_control(mentor_selected)
        start = bool(takeover) and not self._in_takeover
        self.pending = TakeoverStep(
            agent_action=a_av, behavior_action=executed, intervention=bool(takeover), intervention_start=start,
            intervention_cost=takeover_cost(a_av, executed) if start else 0.0, mentor_action=mentor_action,
            physics_action=physics_action, mentor_selected=mentor_selected and bool(takeover), judged=judged)
        return self.pending

    def settle(self, executed_action, mentor_selected: bool) -> TakeoverStep:
        """A judged pending decision (``propose_physics``): what the selection outside the core executed,
        ``executed_action`` ``(A,)`` and whether it was the mentor's; the takeover cost follows it."""
        d = self.pending
        if d is None or not d.judged:
            raise RuntimeError(f"{self.owner}: settle() needs a pending decision proposed for selection")
        executed = np.array(executed_action, dtype=np.float32).reshape(d.behavior_action.shape)
        self.pending = replace(d, behavior_action=executed, mentor_selected=bool(mentor_selected) and d.intervention,
                               intervention_cost=takeover_cost(d.agent_action, executed) if d.intervention_start
                               else 0.0)
        if d.intervention and self.total_steps >= self.warmup_steps:
            self._show_control(bool(mentor_selected))
        return self.pending

    def _show_control(self, mentor_selected: bool) -> None:
        show = getattr(self.mentor, "show_control", None)
        if show is not None:  # a person's window shows who drives now
            show("HUMAN" if mentor_selected else "PHYSICS")

    def commit(self) -> TakeoverStep:
        """The simulator executed the pending decision: advance the takeover state; returns the decision."""
        d = self.pending
        if d is None:
            raise RuntimeError(f"{self.owner}: a step without a decision (was the action set?)")
        self._in_takeover = d.intervention
        self._previous_choice = d.mentor_selected
        self.total_steps += 1
        self.pending = None
        return d

    def _sanitized(self, agent_action) -> np.ndarray:
        a_av = np.array(agent_action, dtype=np.float32)  # a copy: the caller's buffer may be reused
        if a_av.ndim != 1:
            raise ValueError(f"{self.owner} drives one env; got action shape {tuple(a_av.shape)}")
        if not np.isfinite(a_av).all():  # a diverged actor: never executed as proposed
            warnings.warn(f"{self.owner}: the agent proposed {a_av.tolist()}; its non-finite entries "
                          "are executed as 0", RuntimeWarning, stacklevel=4)
            a_av = np.where(np.isfinite(a_av), a_av, np.float32(0.0))
        return a_av

    def _select(self, env, observation, mentor_action, physics_action) -> tuple[np.ndarray, bool]:
        previous = self._previous_choice if self._in_takeover else None
        # Only a value source that forecasts from the simulator hears it (a selector may not take ``env``).
        kwargs = {"env": env} if getattr(getattr(self.selector, "q_ensemble", None), "needs_env", False) else {}
        hybrid, chosen = self.selector.select(_as_tensor(observation), torch.as_tensor(mentor_action),
                                              torch.as_tensor(physics_action), previous, **kwargs)
        return hybrid.numpy().astype(np.float32), bool(chosen.item())

    def _driver_action(self, observation, env, shape: tuple[int, ...]) -> np.ndarray:
        obs = _as_tensor(observation).detach().cpu().numpy().astype(np.float32)
        action = np.asarray(self.warmup_driver(obs, env), dtype=np.float32)
        if action.shape != shape or not np.isfinite(action).all():
            raise ValueError(f"warmup_driver returned {action.tolist()} (shape {action.shape}); expected a finite "
                             f"action of shape {shape}")
        return action


def _as_tensor(observation) -> torch.Tensor:
    """A tensor observation as it is (the transform's); an array one (a gymnasium env's) as float32."""
    if isinstance(observation, torch.Tensor):
        return observation
    return torch.as_tensor(np.asarray(observation, dtype=np.float32))


__all__ = ["OUT_KEYS", "TakeoverCore", "TakeoverStep", "takeover_cost", "takeover_specs", "takeover_tensors"]
