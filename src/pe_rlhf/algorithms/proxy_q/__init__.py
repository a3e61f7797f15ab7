"""The proxy-Q method (PE-RLHF, HACO, HAIM-DRL) and nothing else. Its learner (:mod:`~.trainer`:
``ProxyQLearner``; :mod:`~.steps`, :mod:`~.background_updates`), its builders (:mod:`~.builders`,
:mod:`~.model_builders`: the env with takeovers, the collectors, ``PERLHFLoss``; :mod:`~.takeover_replay`,
:mod:`~.value_expert`), its config (:mod:`~.config_schema`, :mod:`~.config_profiles`, :mod:`~.config`), its entry
point (:mod:`~.recipe`) and the loading of a trained agent (:mod:`~.trained_policy`).

What every method shares lives below it, in :mod:`pe_rlhf.runtime`: the run loop and checkpoints, the config
machinery, the journals, loggers, plots and video, the gradient step and the recipes' command line."""
