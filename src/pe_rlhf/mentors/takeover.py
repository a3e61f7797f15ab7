"""The takeover (switch) rule of simulated mentors: likelihood test, danger check, minimum span.

A mentor that knows its own action ``m`` holds a diagonal Gaussian belief
``N(m, diag(sigma^2))`` over acceptable actions. The agent's action ``a`` is *unlikely*
when it falls outside the central ``free_level`` probability region of that Gaussian:

    d^2 = sum_i ((a_i - m_i) / sigma_i)^2  >  q = F^{-1}_{chi^2(2)}(free_level)

``d^2`` is the squared Mahalanobis distance, chi-square distributed with 2 degrees of
freedom under the Gaussian, whose CDF is ``F(x) = 1 - exp(-x / 2)``; hence the closed form
``q = -2 ln(1 - free_level)`` (5.99 at 0.95). This is HACO's ``free_level`` rule for
simulated mentors, with the mentor's own action as the mean.

Independently of the likelihood, a *danger* check fires a takeover: the agent's action
is held for ``horizon`` seconds on the ego's kinematic bicycle model (highway-env's,
``dt`` steps; no reversing), with other road users at constant velocity and obstacles
standing, and fires if the ego's box (grown by ``margin`` m) overlaps another's or the
ego's centre leaves the road (``road.network.is_on_road(pos, road_margin)``) at least
one rollout step sooner than with the mentor's own action held the same way (a hazard the
mentor's plan meets too is an artefact of holding an action constant: a lane change's
steering held for a second leaves the road). It also fires when the time-to-collision
with the leader in the ego's lane is under ``ttc_min`` seconds while the agent brakes
less than the mentor would (throttle more than 0.1 above the mentor's).

A *stall* test fires too: the ego has been slower than ``stall_speed`` m/s for ``stall_steps``
consecutive steps while the mentor's own plan accelerates (throttle 0.3 above the agent's): a car
waiting for ever behind a broken-down vehicle is taken over, as a person would.

Once fired, control is held for at least ``min_span`` steps (a human's reaction and
hand-back time), then handed back on the first step where the agent's action is likely
again and not dangerous. Deterministic; no random numbers.

Calibration (``benchmarks/ensemble_selection.py --takeover-rates``, train scenes): the belief's width
``sigma`` decides how much *style* a mentor tolerates. With HACO's tight (0.15, 0.3) the professional took
over IDM-MOBIL that sees obstacles (0.98 test success) at 45% of its steps: lane-change timing and speed
choice, not danger. The default (0.6, 0.6) tolerates style and still takes over a random driver nearly
always; ``sigma=(0.15, 0.3)`` and ``stall_steps=0`` give the previous rule.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pe_rlhf.envs.action import action_to_controls
from pe_rlhf.envs.perception import ego_lane_slot, leader_and_follower, neighbours


def chi2_quantile_2dof(level: float) -> float:
    """Quantile of the chi-square distribution with 2 degrees of freedom: ``-2 ln(1 - level)``."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"free_level must be in (0, 1), got {level!r}")
    return -2.0 * math.log1p(-level)


def _boxes_overlap(c1, h1, l1, w1, c2, h2, l2, w2) -> bool:
    """Separating-axis test for two oriented rectangles (centre, heading [rad], length, width)."""
    d = c2 - c1
    for a in (h1, h1 + math.pi / 2, h2, h2 + math.pi / 2):
        r1 = 0.5 * (l1 * abs(math.cos(h1 - a)) + w1 * abs(math.sin(h1 - a)))
        r2 = 0.5 * (l2 * abs(math.cos(h2 - a)) + w2 * abs(math.sin(h2 - a)))
        if abs(d[0] * math.cos(a) + d[1] * math.sin(a)) > r1 + r2:
            return False
    return True


class TakeoverRule:
    """Decides each step whether the mentor holds control (see the module docstring).

    ``sigma``: per-dimension std of the mentor's belief ``[steering, throttle]`` (normalised
    action units; how much style it tolerates); ``free_level``: probability mass of the accepted
    region; ``min_span``: steps a takeover lasts at least; ``horizon``/``dt`` [s]: danger rollout;
    ``margin`` [m]: clearance added around the ego's box; ``road_margin`` [m]: how far the ego's
    centre may pass a lane edge; ``ttc_min`` [s]: leader time-to-collision alarm;
    ``stall_speed`` [m/s] / ``stall_steps``: the stall test (0 steps: off).
    """

    def __init__(self, sigma=(0.6, 0.6), free_level: float = 0.95, min_span: int = 10,
                 horizon: float = 1.2, dt: float = 0.1, margin: float = 0.3, road_margin: float = 0.5,
                 ttc_min: float = 1.5, stall_speed: float = 2.0, stall_steps: int = 20, patience: int = 1):
        self.sigma = np.asarray(sigma, dtype=np.float64).reshape(2)
        if not np.all(self.sigma > 0):
            raise ValueError(f"sigma must be positive, got {self.sigma.tolist()}")
        if not (isinstance(min_span, int) and min_span >= 1):
            raise ValueError(f"min_span must be an integer >= 1, got {min_span!r}")
        if horizon <= 0 or dt <= 0:
            raise ValueError(f"horizon and dt must be positive, got {horizon!r}, {dt!r}")
        self.free_level, self.threshold = float(free_level), chi2_quantile_2dof(free_level)
        self.min_span, self.horizon, self.dt = min_span, float(horizon), float(dt)
        self.margin, self.road_margin, self.ttc_min = float(margin), float(road_margin), float(ttc_min)
        if not (isinstance(stall_steps, int) and stall_steps >= 0):
            raise ValueError(f"stall_steps must be an integer >= 0 (0: off), got {stall_steps!r}")
        self.stall_speed, self.stall_steps = float(stall_speed), stall_steps
        if not (isinstance(patience, int) and patience >= 1):
            raise ValueError(f"patience must be an integer >= 1, got {patience!r}")
        self.patience = patience
        self.unlikely_streak = 0  # consecutive steps the agent's action was unlikely
        self.stalled = 0  # consecutive steps slower than stall_speed while the mentor's plan accelerates
        self.active = False
        self.span = 0  # steps the current takeover has lasted
        self.takeovers = 0  # takeovers started (rising edges)
        self.last_reason: str | None = None  # "unlikely", "collision", "off_road", "ttc" or None

    def reset(self) -> None:
        """Release control (episode start); the takeover count is kept."""
        self.active, self.span, self.last_reason, self.stalled, self.unlikely_streak = False, 0, None, 0, 0

    # -- the two tests -----------------------------------------------------------------
    def mahalanobis2(self, agent_action, mentor_action) -> float:
        """Squared Mahalanobis distance of the agent's action under ``N(mentor_action, sigma^2)``."""
        z = (np.asarray(agent_action, np.float64).reshape(2) - np.asarray(mentor_action, np.float64).reshape(2))
        return float(np.sum((z / self.sigma) ** 2))

    def unlikely(self, agent_action, mentor_action) -> bool:
        """True when the agent's action lies outside the central ``free_level`` region."""
        return self.mahalanobis2(agent_action, mentor_action) > self.threshold

    def danger(self, env, agent_action, mentor_action=None) -> str | None:
        """Why holding ``agent_action`` is dangerous (``collision``/``off_road``/``ttc``), or None.
        (``step`` adds ``unlikely`` and ``stall``.)

        With ``mentor_action`` given, a rollout hazard counts only if it comes at least one
        rollout step sooner than the mentor's own action held the same way would meet one:
        holding any action constant is an approximation (a lane change's full steering held
        for a second leaves the road), and a hazard the mentor's plan shares is not the
        agent's fault.
        """
        env = getattr(env, "unwrapped", env)
        reason, t_agent = self.rollout(env, agent_action)
        if reason is not None and mentor_action is not None:
            _, t_mentor = self.rollout(env, mentor_action)
            if t_agent > t_mentor - self.dt + 1e-9:
                reason = None
        if reason is None and mentor_action is not None \
                and float(agent_action[1]) > float(mentor_action[1]) + 0.1 and self._ttc(env) < self.ttc_min:
            reason = "ttc"
        return reason

    def rollout(self, env, action) -> tuple[str | None, float]:
        """Hold ``action`` for ``horizon`` s: (``collision``/``off_road``, time [s]) of the first hazard,
        or (None, inf). The rollout stops early when the ego would reach the destination."""
        env = getattr(env, "unwrapped", env)
        ego = env.vehicle
        steering, accel = action_to_controls(action)
        beta = math.atan(0.5 * math.tan(steering))
        reach = ego.speed * self.horizon + 30.0 * self.horizon + 10.0
        others = [o for o in list(env.road.vehicles) + list(env.road.objects)
                  if o is not ego and getattr(o, "solid", True) and np.linalg.norm(o.position - ego.position) < reach]
        pos, heading, speed = np.array(ego.position, dtype=np.float64), float(ego.heading), float(ego.speed)
        length, width = ego.LENGTH + 2 * self.margin, ego.WIDTH + 2 * self.margin
        ego_r = 0.5 * math.hypot(length, width)
        to_go, travelled = env.route.length - env.progress - 5.0, 0.0  # the env succeeds 5 m before the end
        for k in range(1, int(round(self.horizon / self.dt)) + 1):
            travelled += speed * self.dt
            if travelled >= to_go:
                break
            pos = pos + speed * self.dt * np.array([math.cos(heading + beta), math.sin(heading + beta)])
            heading += speed * math.sin(beta) / (ego.LENGTH / 2) * self.dt
            speed = min(max(speed + accel * self.dt, 0.0), ego.MAX_SPEED)
            t = k * self.dt
            for o in others:
                c = np.asarray(o.position, np.float64) + np.asarray(o.velocity, np.float64) * t
                if np.linalg.norm(c - pos) > ego_r + 0.5 * math.hypot(o.LENGTH, o.WIDTH):
                    continue
                if _boxes_overlap(pos, heading, length, width, c, float(o.heading), o.LENGTH, o.WIDTH):
                    return "collision", t
            if not env.road.network.is_on_road(pos, self.road_margin):
                return "off_road", t
        return None, math.inf

    def _stalls(self, env, agent_action, mentor_action) -> bool:
        """Advance the stall counter; True once the car has stalled for ``stall_steps`` steps."""
        if not self.stall_steps:
            return False
        speed = float(getattr(getattr(env, "unwrapped", env), "vehicle").speed)
        pushing = float(np.asarray(mentor_action).reshape(2)[1]) > float(agent_action[1]) + 0.3
        self.stalled = self.stalled + 1 if speed < self.stall_speed and pushing else 0
        return self.stalled >= self.stall_steps

    @staticmethod
    def _ttc(env) -> float:
        """Time-to-collision [s] with the leader in the ego's lane slot (inf if not closing)."""
        slot, _ = ego_lane_slot(env)
        lead, _ = leader_and_follower(neighbours(env, include_obstacles=True, radius=80.0), slot,
                                      env.progress, env.route.lanes)
        if lead is None:
            return math.inf
        gap = lead.s - env.progress - (lead.length + env.vehicle.LENGTH) / 2
        closing = env.vehicle.speed - lead.speed
        return max(gap, 0.0) / closing if closing > 0 else math.inf

    # -- the switch ----------------------------------------------------------------------
    def step(self, env, agent_action, mentor_action) -> bool:
        """Advance one env step; True while the mentor holds control."""
        agent_action = np.asarray(agent_action, dtype=np.float64).reshape(2)
        unlikely = self.unlikely(agent_action, mentor_action)
        self.unlikely_streak = self.unlikely_streak + 1 if unlikely else 0
        # while in control any unlikely action keeps it; to take over, it must have lasted `patience` steps
        reason = "unlikely" if unlikely and (self.active or self.unlikely_streak >= self.patience) else None
        if reason is None:
            reason = self.danger(env, agent_action, mentor_action)
        if reason is None and self._stalls(env, agent_action, mentor_action):
            reason = "stall"
        self.last_reason = reason
        if self.active:
            if self.span >= self.min_span and reason is None:
                self.active, self.span = False, 0
            else:
                self.span += 1
        elif reason is not None:
            self.active, self.span = True, 1
            self.takeovers += 1
        return self.active

    def state_dict(self) -> dict[str, Any]:
        return {"active": self.active, "span": self.span, "takeovers": self.takeovers, "stalled": self.stalled}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.active, self.span = bool(state["active"]), int(state["span"])
        self.takeovers = int(state.get("takeovers", 0))
        self.stalled = int(state.get("stalled", 0))
