"""Networks: SAC-style and TD3-style actors, critics, and the Q-ensemble estimator."""

from pe_rlhf.modules.networks import QValueNet, make_actor, make_deterministic_actor, make_qvalue
from pe_rlhf.modules.ensemble_training import EnsembleSchedule, add_next_actions
from pe_rlhf.modules.q_ensemble import QEnsemble, load_q_ensemble, q_ensemble_from_critics, save_q_ensemble

__all__ = ["EnsembleSchedule", "QEnsemble", "QValueNet", "add_next_actions", "load_q_ensemble", "make_actor",
           "make_deterministic_actor", "make_qvalue", "q_ensemble_from_critics", "save_q_ensemble"]
