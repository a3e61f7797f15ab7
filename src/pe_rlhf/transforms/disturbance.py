"""``TrafficDisturbanceCost``: HAIM-DRL's cost for disturbing the traffic behind the ego by hard braking.

After each step the transform measures the ego's deceleration over the step,
``(v_before - v_after) / dt`` [m/s^2] with ``dt`` the policy step. A *braking event* is a run of
consecutive steps whose deceleration exceeds ``threshold`` (default 5 m/s^2). At the first step of an
event, unless the mentor drove that step (``("next", "intervention")``; no such key = the agent
drove), it predicts with IDM how much the vehicles following the ego slow down, and charges

    ``C_dist = 1 - exp(-mean_i dv_i)``,  ``dv_i = max(0, v_i(0) - min_{0<=t<=horizon} v_i(t))`` [m/s]

at that step, 0 at every other step. The followers are the vehicles (not obstacles) occupying the
ego's lane slot within ``follower_range`` metres behind it, simulated as a platoon: the ego keeps
braking at the measured rate until it stops or the horizon ends, each follower drives IDM
(:func:`~pe_rlhf.physics.idm.idm_acceleration`, its own ``target_speed`` as desired speed) behind the
vehicle ahead of it. ``v_i(0)`` is the speed it has now, i.e. the loss is counted against the follower
keeping its speed; the slowing down the same prediction gives with the ego holding its speed is
subtracted, as it is not the braking's doing (:func:`predict_speed_loss`). No follower: cost 0.

Writes under ``next`` (float32, trailing dim 1): ``disturbance_cost`` ``(1,)`` in [0, 1). Reads the
``intervention`` flag ``(1,)`` written by an :class:`~pe_rlhf.transforms.InterventionTransform`
placed before this one in the same env (without one, every step counts as the agent's). The
prediction reads the simulator's true state (privileged), like the physics policy; put the transform
inside each worker's env factory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from pe_rlhf.envs.torchrl_env import unwrap
from pe_rlhf.physics.idm import IDMParams, idm_acceleration
from pe_rlhf.envs.perception import ego_lane_slot, neighbours, occupies

PREDICTION_DT = 0.1  # [s] integration step of the IDM platoon prediction


@dataclass(frozen=True)
class PlatoonCar:
    """A follower as the prediction sees it: route progress of its centre ``s`` [m], ``speed`` and
    ``desired_speed`` [m/s], ``length`` [m]."""

    s: float
    speed: float
    desired_speed: float
    length: float


def _lowest_speeds(ego_s: float, ego_speed: float, ego_length: float, deceleration: float,
                   followers: list[PlatoonCar], horizon: float, params: IDMParams | None, dt: float) -> list[float]:
    """Each follower's lowest speed [m/s] over ``[0, horizon]`` behind an ego braking at ``deceleration``
    until it stops (explicit Euler on speeds, then positions, step ``dt``)."""
    ego_v = ego_speed
    s = [f.s for f in followers]
    v = [f.speed for f in followers]
    low = list(v)
    for _ in range(max(1, math.ceil(horizon / dt - 1e-9))):
        acc = []
        for i, f in enumerate(followers):
            ahead_s, ahead_v, ahead_len = (ego_s, ego_v, ego_length) if i == 0 else (s[i - 1], v[i - 1],
                                                                                     followers[i - 1].length)
            gap = ahead_s - s[i] - 0.5 * (ahead_len + f.length)
            acc.append(idm_acceleration(v[i], max(f.desired_speed, 1.0), gap, ahead_v, params))
        ego_v = max(0.0, ego_v - deceleration * dt)
        ego_s += ego_v * dt
        for i in range(len(followers)):
            v[i] = max(0.0, v[i] + acc[i] * dt)
            s[i] += v[i] * dt
            low[i] = min(low[i], v[i])
    return low


def predict_speed_loss(ego_s: float, ego_speed: float, ego_length: float, deceleration: float,
                       followers: list[PlatoonCar], horizon: float, params: IDMParams | None = None,
                       dt: float = PREDICTION_DT) -> list[float]:
    """Each follower's predicted speed loss [m/s] over ``horizon`` [s] caused by the ego's braking.

    The ego (route progress ``ego_s`` [m], speed [m/s], length [m]) brakes at ``deceleration`` [m/s^2,
    positive] until it stops; ``followers`` are ordered nearest first, each following the one before it
    (the first follows the ego) with IDM. The loss is ``max(0, low_hold - low_brake)``, the lowest speed
    a follower keeps while the ego holds its speed minus the lowest while it brakes (both including the
    speed it has now): ``v(0) - min_t v(t)`` for a follower the ego does not otherwise slow down, and no
    charge for the slowing down the follower would do anyway (closing in already, or this IDM's
    parameters wanting a longer gap than the simulator's traffic keeps).
    """
    brake = _lowest_speeds(ego_s, ego_speed, ego_length, deceleration, followers, horizon, params, dt)
    hold = _lowest_speeds(ego_s, ego_speed, ego_length, 0.0, followers, horizon, params, dt)
    return [max(0.0, h - b) for h, b in zip(hold, brake)]


def disturbance_cost(speed_losses: list[float]) -> float:
    """``1 - exp(-mean speed loss)`` in [0, 1); 0 without followers."""
    if not speed_losses:
        return 0.0
    return float(1.0 - math.exp(-sum(speed_losses) / len(speed_losses)))


def followers_in_lane(env, follower_range: float) -> list[PlatoonCar]:
    """Vehicles occupying the ego's lane slot within ``follower_range`` metres behind it (centre to
    centre along the route), nearest first."""
    lane, _ = ego_lane_slot(env)
    ego_s = float(env.progress)
    out = []
    for n in neighbours(env, include_obstacles=False, radius=follower_range + 10.0):
        if n.s < ego_s and ego_s - n.s <= follower_range and occupies(n, lane, env.route.lanes):
            desired = float(getattr(n.obj, "target_speed", n.speed) or n.speed)
            out.append(PlatoonCar(float(n.s), max(float(n.speed), 0.0), desired, float(n.length)))
    return sorted(out, key=lambda c: -c.s)


class TrafficDisturbanceCost(Transform):
    """HAIM-DRL's traffic-disturbance cost at the start of each hard-braking event (module docstring).

    Args:
        threshold: deceleration [m/s^2] above which a step is hard braking (default 5).
        horizon: prediction horizon [s] of the followers' slowdown (default 3).
        follower_range: how far behind the ego [m] a vehicle in its lane counts as a follower (default 60).
        idm_params: the followers' IDM (default :class:`~pe_rlhf.physics.idm.IDMParams`, the paper's).
        intervention_key: the step output flagging a takeover (under ``next``).
    """

    def __init__(self, threshold: float = 5.0, horizon: float = 3.0, follower_range: float = 60.0,
                 idm_params: IDMParams | None = None, intervention_key: str = "intervention"):
        super().__init__(in_keys=[], out_keys=["disturbance_cost"])
        for name, value in (("threshold", threshold), ("horizon", horizon), ("follower_range", follower_range)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value > 0):
                raise ValueError(f"TrafficDisturbanceCost {name}={value!r} is invalid: must be a finite number > 0")
        self.threshold, self.horizon, self.follower_range = float(threshold), float(horizon), float(follower_range)
        self.idm_params = idm_params
        self.intervention_key = intervention_key
        self._speed_before: float | None = None
        self._braking = False  # the previous step was hard braking (an event is running)
        self.last_deceleration = 0.0  # [m/s^2] of the latest step (diagnostics, tests)

    @property
    def driving_env(self):
        return unwrap(self.parent)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._speed_before, self._braking, self.last_deceleration = None, False, 0.0
        tensordict_reset.set("disturbance_cost", torch.zeros(1, dtype=torch.float32))
        return tensordict_reset

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # read just before the simulator moves: whatever set the ego's state since the last step counts
        self._speed_before = float(self.driving_env.vehicle.speed)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        env = self.driving_env
        speed = float(env.vehicle.speed)
        before = speed if self._speed_before is None else self._speed_before
        self.last_deceleration = (before - speed) * float(env.world.policy_frequency)
        hard = self.last_deceleration > self.threshold
        cost = 0.0
        takeover = next_tensordict.get(self.intervention_key, None)
        if hard and not self._braking and not (takeover is not None and bool(takeover.any())):
            followers = followers_in_lane(env, self.follower_range)
            if followers:
                losses = predict_speed_loss(float(env.progress), speed, float(env.vehicle.LENGTH),
                                            self.last_deceleration, followers, self.horizon, self.idm_params)
                cost = disturbance_cost(losses)
        self._braking, self._speed_before = hard, None
        next_tensordict.set("disturbance_cost", torch.tensor([cost], dtype=torch.float32))
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec["disturbance_cost"] = Unbounded((1,), dtype=torch.float32)
        return observation_spec
