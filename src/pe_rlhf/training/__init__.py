"""Training: recipe helpers shared by the recipes (config, builders, logging; checkpoints are :mod:`pe_rlhf.runtime`'s)."""
