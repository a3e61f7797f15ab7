"""Losses: ``PERLHFLoss`` (PE-RLHF, HACO and ablations as flags)."""

from pe_rlhf.objectives.perlhf import PERLHFLoss

__all__ = ["PERLHFLoss"]
