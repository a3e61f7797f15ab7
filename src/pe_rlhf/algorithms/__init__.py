"""The algorithms layer: one registry of the training methods (:data:`ALGORITHMS`), each a recipe plus the
overrides that make it that method. Apps (sweeps, compare, the command line) look methods up here.

The registry is imported on first use (it reads the baselines' table, which imports torch), so that
``from pe_rlhf.algorithms.names import ...`` stays free for a command line that must start fast.
"""

from pe_rlhf.algorithms.names import EVALUATE, PROXY_Q, PROXY_Q_RECIPES

_REGISTRY_NAMES = ("ALGORITHMS", "Algorithm", "algorithm", "recipe_names")


def __getattr__(name: str):
    if name in _REGISTRY_NAMES:
        from pe_rlhf.algorithms import registry

        return getattr(registry, name)
    raise AttributeError(f"module 'pe_rlhf.algorithms' has no attribute {name!r}")


__all__ = ["ALGORITHMS", "EVALUATE", "PROXY_Q", "PROXY_Q_RECIPES", "Algorithm", "algorithm", "recipe_names"]
