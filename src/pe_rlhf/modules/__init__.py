"""Networks: SAC-style actor, critics, and the Q-ensemble estimator."""

from pe_rlhf.modules.networks import QValueNet, make_actor, make_qvalue
from pe_rlhf.modules.q_ensemble import QEnsemble

__all__ = ["QEnsemble", "QValueNet", "make_actor", "make_qvalue"]
