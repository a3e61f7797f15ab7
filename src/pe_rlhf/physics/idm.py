"""Intelligent Driver Model (IDM) for longitudinal control (Treiber et al., 2000).

Units: speeds in m/s, gaps in m (bumper to bumper), accelerations in m/s^2,
times in s. Pure maths: plain floats, no simulator dependency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass(frozen=True)
class IDMParams:
    """IDM parameters (PE-RLHF paper values as defaults).

    Units: max_acceleration, comfortable_braking, max_braking in m/s^2 (all
    positive magnitudes); minimum_gap in m; time_headway in s; exponent
    dimensionless. ``max_braking`` is the physical deceleration limit the
    output is clipped to (emergencies).
    """

    max_acceleration: float = 2.0
    comfortable_braking: float = 5.0
    minimum_gap: float = 10.0
    time_headway: float = 1.5
    exponent: float = 4.0
    max_braking: float = 6.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"IDMParams.{f.name} must be finite and > 0, got {value!r}")


def _params(params: IDMParams | None) -> IDMParams:
    return IDMParams() if params is None else params


def idm_desired_gap(
    speed: float, approach_rate: float, params: IDMParams | None = None
) -> float:
    """Desired dynamic gap s* = s0 + max(0, v*T + v*dv / (2*sqrt(a*b))).

    Units: speed v in m/s, approach_rate dv = v - v_leader in m/s (positive when
    closing in); returns metres. The max(0, .) clamp is the standard Treiber
    form: it keeps s* >= s0 even when the leader pulls away quickly.
    """
    p = _params(params)
    dynamic = speed * p.time_headway + speed * approach_rate / (
        2.0 * math.sqrt(p.max_acceleration * p.comfortable_braking)
    )
    return p.minimum_gap + max(0.0, dynamic)


def idm_acceleration(
    speed: float,
    desired_speed: float,
    gap: float | None = None,
    leader_speed: float | None = None,
    params: IDMParams | None = None,
) -> float:
    """IDM acceleration a*(1 - (v/v0)^delta - (s*/s)^2), clipped to [-b_max, a_max].

    Units: speed, desired_speed (v0 > 0), leader_speed in m/s; gap in m; returns
    m/s^2. ``gap=None`` means free road (leader_speed is ignored). A gap with
    ``leader_speed=None`` is treated as a stationary obstacle. A gap <= 0
    (overlap/collision) returns -max_braking.
    """
    p = _params(params)
    if not desired_speed > 0:
        raise ValueError(f"desired_speed must be > 0, got {desired_speed!r}")
    free_term = 1.0 - (max(speed, 0.0) / desired_speed) ** p.exponent
    if gap is None:
        acc = p.max_acceleration * free_term
    elif gap <= 0:
        return -p.max_braking
    else:
        v_lead = 0.0 if leader_speed is None else leader_speed
        s_star = idm_desired_gap(speed, speed - v_lead, p)
        acc = p.max_acceleration * (free_term - (s_star / gap) ** 2)
    return float(min(p.max_acceleration, max(-p.max_braking, acc)))


def idm_equilibrium_gap(
    speed: float, desired_speed: float, params: IDMParams | None = None
) -> float:
    """Steady-state gap behind a leader at the same speed (zero IDM acceleration).

    Units: speed, desired_speed in m/s; returns metres.
    s_e = s*(v, 0) / sqrt(1 - (v/v0)^delta); ``inf`` when v >= v0.
    """
    p = _params(params)
    if not desired_speed > 0:
        raise ValueError(f"desired_speed must be > 0, got {desired_speed!r}")
    free_term = 1.0 - (max(speed, 0.0) / desired_speed) ** p.exponent
    if free_term <= 0:
        return math.inf
    return idm_desired_gap(speed, 0.0, p) / math.sqrt(free_term)
