"""Training: the recipes' config, builders and logging, and the proxy-Q learner (checkpoints and the run loop:
:mod:`pe_rlhf.runtime`)."""
