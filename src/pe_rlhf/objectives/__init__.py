"""TorchRL ``LossModule``s: PE-RLHF's proxy-Q loss (HACO without physics) and
PVP's bounded proxy values, the Q-ensemble estimator's TD loss
and its fit, the optimiser and target steps of every learner, and what TorchRL lacks for the safe-RL baselines
(SAC-Lag, PPO-Lag, CPO). Each keeps TorchRL's ``LossModule`` contract (``in_keys``, ``out_keys``,
``select_out_keys``, keyword calls, ``make_value_estimator``); :mod:`~pe_rlhf.objectives.contract` gives it to
the losses that subclass ``LossModule`` directly."""

from pe_rlhf.objectives.contract import KeyedLoss, UnsupportedValueEstimator
from pe_rlhf.objectives.cpo import CPOLoss
from pe_rlhf.objectives.lagrangian import LagrangeMultiplier, PPOLagLoss, SACLagLoss
from pe_rlhf.objectives.optimizer_steps import ForeachSoftUpdate, make_adam
from pe_rlhf.objectives.perlhf import PERLHFLoss
from pe_rlhf.objectives.proxy_value import ProxyValueLoss
from pe_rlhf.objectives.q_ensemble_fit import fit_q_ensemble
from pe_rlhf.objectives.q_ensemble_td import QEnsembleTDLoss

__all__ = ["CPOLoss", "ForeachSoftUpdate", "KeyedLoss", "LagrangeMultiplier", "PERLHFLoss", "PPOLagLoss",
           "ProxyValueLoss", "QEnsembleTDLoss", "SACLagLoss", "UnsupportedValueEstimator", "fit_q_ensemble",
           "make_adam"]
