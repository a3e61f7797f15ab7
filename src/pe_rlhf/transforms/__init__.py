"""TorchRL transforms of PE-RLHF: mentor intervention, hybrid action selection, the runtime safety shield,
real-time pacing, and HAIM-DRL's traffic-disturbance cost."""

from pe_rlhf.transforms.disturbance import TrafficDisturbanceCost
from pe_rlhf.transforms.hybrid_selection import HybridSelectionTransform
from pe_rlhf.transforms.intervention import InterventionTransform, takeover_cost
from pe_rlhf.transforms.pacing import RealtimePacing
from pe_rlhf.transforms.selector import HybridActionSelector
from pe_rlhf.transforms.shield import LATCH_RELEASE_SPEED, SHIELD_PHYSICS, SafetyShield, ShieldCore

__all__ = ["LATCH_RELEASE_SPEED", "SHIELD_PHYSICS", "HybridActionSelector", "HybridSelectionTransform",
           "InterventionTransform", "RealtimePacing", "SafetyShield", "ShieldCore", "TrafficDisturbanceCost",
           "takeover_cost"]
