"""pe-rlhf: Physics-enhanced RL with Human Feedback, as TorchRL components."""

__version__ = "0.1.0"
