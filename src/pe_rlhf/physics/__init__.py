"""Physics policy: IDM longitudinal + MOBIL lateral control."""

from pe_rlhf.physics.idm import (
    IDMParams,
    idm_acceleration,
    idm_desired_gap,
    idm_equilibrium_gap,
)
from pe_rlhf.physics.mobil import (
    LaneChangeAccelerations,
    MOBILParams,
    mobil_choose_lane,
    mobil_incentive,
    mobil_safe,
    mobil_should_change,
)

__all__ = [
    "IDMParams",
    "LaneChangeAccelerations",
    "MOBILParams",
    "idm_acceleration",
    "idm_desired_gap",
    "idm_equilibrium_gap",
    "mobil_choose_lane",
    "mobil_incentive",
    "mobil_safe",
    "mobil_should_change",
]

from pe_rlhf.physics.policy import IDMMobilPolicy, PhysicsConfig  # noqa: E402

__all__ += ["IDMMobilPolicy", "PhysicsConfig"]

from pe_rlhf.physics.safety import SafetyForecastConfig, SafetyForecastValue, time_to_failure  # noqa: E402

__all__ += ["SafetyForecastConfig", "SafetyForecastValue", "time_to_failure"]
