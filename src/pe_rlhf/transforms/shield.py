"""``SafetyShield``: a runtime shield (Simplex) for any driving policy, as a TorchRL transform.

Every step, the policy's ``action`` and the physics policy's (the fallback: IDM-MOBIL with MOBIL seeing obstacles,
``SHIELD_PHYSICS``) are scored by the physics forecast (:class:`~pe_rlhf.physics.SafetyForecastValue`: seconds until
the action, held 1 s then followed by a recovery, leads to a crash or off the road). The shield executes physics'
action when the policy's fails more than ``threshold`` seconds sooner than physics' and hands the wheel back when it
no longer does. The rule is :class:`~pe_rlhf.transforms.HybridActionSelector`'s, with the policy as the mentor
(``epsilon_select = -threshold``), ``reference="physics_or_recovery"`` (physics' action, or braking at once where
that is forecast safer: the fallback is what runs), ``strict_in_danger`` (no slack where the fallback itself is
forecast to fail) and ``persistence="latch"``: once the shield has acted it keeps the wheel until the policy's
action, *repeated* over the whole forecast (as a policy that repeats it will execute it), is no longer forecast to
fail sooner than physics' by more than ``threshold``. Without the latch a policy that repeats a dangerous action
passes the one-step check at every step while the sequence ends in a crash.

Composes on a plain ``TransformedEnv`` over the driving env, whatever writes ``action``::

    env = TransformedEnv(make_env(config), SafetyShield())
    env.rollout(500, policy)

Reads ``action`` (A,) on the inverse path and replaces it where the shield acts. Writes under ``next``
(``out_keys``, renamable, in this order; names in :mod:`pe_rlhf.transforms.keys`):

============================  ==================================================================
``shield_override`` (1,)      bool: the shield executed physics' action this step
``shielded_action`` (A,)      float32: the action executed (the policy's or physics')
``policy_time_to_failure``    float32 (1,): the forecast of the policy's action [s] (horizon: safe)
``physics_time_to_failure``   float32 (1,): the forecast of physics' action [s]
============================  ==================================================================

The decision itself is :class:`ShieldCore`'s, shared with the gymnasium face
:class:`~pe_rlhf.wrappers.SafetyShieldWrapper`. Unbatched envs only (the forecast reads one simulator).
What the shield guarantees and what it cannot see: docs/guide/shield.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from pe_rlhf.physics import IDMMobilPolicy, PhysicsConfig, SafetyForecastConfig, SafetyForecastValue
from pe_rlhf.transforms.intervention import simulator_of
from pe_rlhf.transforms.keys import SHIELD_OUT_KEYS
from pe_rlhf.transforms.selector import HybridActionSelector

DEFAULT_THRESHOLD = 0.5  # [s] the selector's -epsilon_select (docs/results/claims: the forecast's calibration)
# [m/s] with persistence="latch": a standing car's step is judged alone (docs/experiments/shield-calibration.md: the
# professional steering around an obstacle at walking pace was held behind it, standing, by the latch)
LATCH_RELEASE_SPEED = 0.5
# The fallback: IDM-MOBIL whose MOBIL sees obstacles too, so that a lane change never steers into one. The paper's
# physics (``PhysicsConfig()``: IDM stops for obstacles, MOBIL is blind to them) drove a shielded seek-collision into
# a cone taper on train scene 1; this one held every driver of train scenes 0-9 with no violation, at equal or
# higher success (docs/experiments/shield-calibration.md).
SHIELD_PHYSICS = PhysicsConfig(see_obstacles=True)


def shield_selector(threshold: float = DEFAULT_THRESHOLD, persistence: str = "latch",
                    forecast: SafetyForecastConfig | None = None, reference: str = "physics_or_recovery",
                    strict_in_danger: bool = True) -> HybridActionSelector:
    """The shield's rule: the hybrid selector over the physics forecast with ``epsilon_select = -threshold``,
    ``persistence`` (with ``"latch"``, released where the car stands: ``LATCH_RELEASE_SPEED``), ``reference`` (the
    policy is compared with the better of physics' action and braking at once, and the better one runs) and
    ``strict_in_danger`` (no slack where that fallback itself is forecast to fail):
    :class:`~pe_rlhf.transforms.HybridActionSelector`."""
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not np.isfinite(threshold) \
            or threshold < 0:
        raise ValueError(f"SafetyShield threshold={threshold!r} must be a finite number of seconds >= 0")
    return HybridActionSelector(SafetyForecastValue(forecast), -float(threshold), persistence=persistence,
                                reference=reference, strict_in_danger=strict_in_danger,
                                latch_release_speed=LATCH_RELEASE_SPEED if persistence == "latch" else None)


@dataclass(frozen=True)
class ShieldDecision:
    """One step's decision: the action to execute, whether the shield acted, both forecasts [s], and the
    seconds the decision took (physics and both forecasts)."""

    action: np.ndarray
    override: bool
    policy_time_to_failure: float
    physics_time_to_failure: float
    latency: float


class ShieldCore:
    """The shield's decision, shared by :class:`SafetyShield` and :class:`~pe_rlhf.wrappers.SafetyShieldWrapper`.

    ``decide(env, action)``: ``env`` the ``DrivingEnv`` (privileged: physics and the forecast read its true
    state), ``action`` the policy's ``(2,)``. State: physics' (its lane plan) and the latch, both cleared by
    ``reset(env)`` at each episode start. A non-finite policy action is always overridden.
    """

    def __init__(self, threshold: float = DEFAULT_THRESHOLD, physics=None, selector: HybridActionSelector | None = None,
                 persistence: str = "latch"):
        if selector is not None and not getattr(selector.q_ensemble, "needs_env", False):
            raise ValueError("SafetyShield: selector must read a forecast from the simulator (SafetyForecastValue)")
        self.selector = selector or shield_selector(threshold, persistence)
        self.physics = physics or IDMMobilPolicy(SHIELD_PHYSICS)
        self.threshold = -self.selector.epsilon_select
        self._latch: torch.Tensor | None = None  # (1,) int64: 1 while the shield holds the wheel

    def reset(self, env) -> None:
        reset = getattr(self.physics, "reset", None)
        if callable(reset):
            reset()
        self._latch = None

    def decide(self, env, action) -> ShieldDecision:
        start = time.perf_counter()
        proposed = torch.as_tensor(np.asarray(action, dtype=np.float32).reshape(2))
        physics = torch.as_tensor(np.asarray(self.physics(env), dtype=np.float32).reshape(2))
        obs = torch.zeros(1)  # the forecast reads the simulator, not the observation
        hybrid, chosen, self._latch, t_policy, t_physics = self.selector.judge(
            obs, proposed, physics, None, self._latch, env=env)
        return ShieldDecision(hybrid.numpy().astype(np.float32), not bool(chosen.item()), float(t_policy.item()),
                              float(t_physics.item()), time.perf_counter() - start)


class SafetyShield(Transform):
    """The runtime shield on the inverse path of a ``TransformedEnv`` (see the module docstring).

    Args:
        threshold: seconds by which the policy's action may fail sooner than physics' before the shield acts.
        physics: the fallback (default ``IDMMobilPolicy(SHIELD_PHYSICS)``: IDM-MOBIL that changes lanes around
            obstacles), called ``physics(sim)``.
        selector: the rule (default :func:`shield_selector` ``(threshold, persistence)``).
        persistence: ``latch`` (default), ``always`` or ``off`` (each step judged alone: the one-step rule).
        in_keys: ``[action]``; out_keys: ``[shield_override, shielded_action, policy_time_to_failure,
            physics_time_to_failure]``.
    """

    def __init__(self, threshold: float = DEFAULT_THRESHOLD, physics=None, selector: HybridActionSelector | None = None,
                 persistence: str = "latch", *, in_keys=("action",), out_keys=SHIELD_OUT_KEYS):
        in_keys, out_keys = list(in_keys), list(out_keys)
        if len(in_keys) != 1 or len(out_keys) != len(SHIELD_OUT_KEYS):
            raise ValueError(f"SafetyShield: in_keys are [action] (got {in_keys}); out_keys are "
                             f"{list(SHIELD_OUT_KEYS)} (got {out_keys})")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.core = ShieldCore(threshold, physics, selector, persistence)
        self.action_key = in_keys[0]
        self.override_key, self.executed_key, self.policy_key, self.physics_key = out_keys
        self._last: ShieldDecision | None = None
        self.latencies: list[float] = []  # seconds per decision since construction (decision latency)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self.core.reset(simulator_of(self.parent))
        for key, spec in self.transform_observation_spec(Composite(shape=tensordict_reset.batch_size)).items():
            tensordict_reset.set(key, spec.zero())
        return tensordict_reset

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # the decision is made on the way to the simulator

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        if action.dim() != 1:
            raise ValueError(f"SafetyShield serves an unbatched env (one simulator); action has shape "
                             f"{tuple(action.shape)}")
        decision = self.core.decide(simulator_of(self.parent), action.detach().cpu().numpy())
        self._last = decision
        self.latencies.append(decision.latency)
        if decision.override:
            tensordict.set(self.action_key, torch.as_tensor(decision.action, dtype=action.dtype,
                                                            device=action.device))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        d = self._last
        next_tensordict.set(self.override_key, torch.tensor([d.override]))
        next_tensordict.set(self.executed_key, tensordict.get(self.action_key).to(torch.float32))
        next_tensordict.set(self.policy_key, torch.tensor([d.policy_time_to_failure], dtype=torch.float32))
        next_tensordict.set(self.physics_key, torch.tensor([d.physics_time_to_failure], dtype=torch.float32))
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        action_shape = self.parent.full_action_spec[self.action_key].shape if self.parent is not None else (2,)
        observation_spec[self.override_key] = Unbounded((1,), dtype=torch.bool)
        observation_spec[self.executed_key] = Unbounded(action_shape, dtype=torch.float32)
        observation_spec[self.policy_key] = Unbounded((1,), dtype=torch.float32)
        observation_spec[self.physics_key] = Unbounded((1,), dtype=torch.float32)
        return observation_spec


__all__ = ["DEFAULT_THRESHOLD", "SafetyShield", "ShieldCore", "ShieldDecision", "shield_selector"]
