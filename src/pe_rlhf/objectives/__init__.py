"""TorchRL ``LossModule``s: PE-RLHF's proxy-Q loss (HACO without physics) and what TorchRL lacks for the
safe-RL baselines (SAC-Lag, PPO-Lag, CPO)."""

from pe_rlhf.objectives.cpo import CPOLoss
from pe_rlhf.objectives.lagrangian import LagrangeMultiplier, PPOLagLoss, SACLagLoss
from pe_rlhf.objectives.perlhf import PERLHFLoss

__all__ = ["CPOLoss", "LagrangeMultiplier", "PERLHFLoss", "PPOLagLoss", "SACLagLoss"]
