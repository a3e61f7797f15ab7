"""Training: recipe helpers shared by the recipes (config, builders, logging, checkpoints)."""
