"""TorchRL transforms of PE-RLHF: mentor intervention and hybrid (mentor vs physics) action selection."""

from pe_rlhf.transforms.intervention import InterventionTransform, takeover_cost
from pe_rlhf.transforms.selector import HybridActionSelector

__all__ = ["HybridActionSelector", "InterventionTransform", "takeover_cost"]
