"""Validated configuration of the driving world."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from pe_rlhf.envs.blocks import BLOCK_TYPES
from pe_rlhf.envs.splits import SPLITS


@dataclass(frozen=True)
class DrivingConfig:
    """Everything that defines the driving world; two envs with equal configs are the same world.

    Densities are per 100 m of route: ``traffic_density`` vehicles per lane,
    ``obstacle_density`` lane-blocking obstacle events (a broken-down car behind a
    warning triangle, or a line of cones). Scenes come from integer seeds; the
    ``train``/``test`` splits are fixed seed ranges (see :mod:`pe_rlhf.envs.splits`).
    """

    traffic_density: float = 0.5
    obstacle_density: float = 1.0
    truck_fraction: float = 0.2
    side_traffic_probability: float = 0.6
    lanes: int = 3
    min_blocks: int = 3
    max_blocks: int = 4
    block_types: tuple[str, ...] = BLOCK_TYPES
    horizon: int = 1000
    simulation_frequency: int = 20
    policy_frequency: int = 10
    lidar_beams: int = 240
    lidar_range: float = 50.0
    lane_features: bool = False
    active_radius: float = 150.0
    split: str | None = "train"

    def __post_init__(self) -> None:
        def bad(name: str, allowed: str) -> None:
            raise ValueError(f"DrivingConfig.{name}={getattr(self, name)!r} is invalid: {allowed}")

        for name in ("lanes", "min_blocks", "max_blocks", "horizon", "simulation_frequency",
                     "policy_frequency", "lidar_beams"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                bad(name, "must be an integer")
        for name in ("traffic_density", "obstacle_density"):
            if not 0 <= getattr(self, name) <= 5:
                bad(name, "must be in [0, 5]")
        for name in ("truck_fraction", "side_traffic_probability"):
            if not 0 <= getattr(self, name) <= 1:
                bad(name, "must be in [0, 1]")
        if not 2 <= self.lanes <= 4:
            bad("lanes", "must be 2, 3 or 4")
        if not 1 <= self.min_blocks <= self.max_blocks <= 10:
            bad("min_blocks", "need 1 <= min_blocks <= max_blocks <= 10")
        object.__setattr__(self, "block_types", tuple(self.block_types))
        unknown = [b for b in self.block_types if b not in BLOCK_TYPES]
        if unknown or not self.block_types:
            bad("block_types", f"unknown {unknown}; allowed: {list(BLOCK_TYPES)}")
        if self.horizon < 1:
            bad("horizon", "must be >= 1")
        if self.policy_frequency < 1 or self.simulation_frequency < 1 \
                or self.simulation_frequency % self.policy_frequency:
            bad("simulation_frequency", "must be a positive multiple of policy_frequency "
                "(highway-env runs int(sim // policy) substeps per action)")
        if self.lidar_beams < 1 or self.lidar_range <= 0:
            bad("lidar_beams", "need lidar_beams >= 1 and lidar_range > 0")
        if self.active_radius <= self.lidar_range:
            bad("active_radius", "must exceed lidar_range so every perceived vehicle is simulated")
        if not isinstance(self.lane_features, bool):
            bad("lane_features", "must be true or false")
        if self.split is not None and self.split not in SPLITS:
            bad("split", f"must be one of {list(SPLITS)} or None")

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> DrivingConfig:
        """Build from a mapping; unknown keys fail with their names."""
        values = dict(values or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown DrivingConfig field(s) {unknown}; known: {sorted(known)}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["block_types"] = list(self.block_types)
        return d
