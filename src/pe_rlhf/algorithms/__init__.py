"""The algorithms layer: every training method, and the one registry of them (:data:`ALGORITHMS`).

- :mod:`~pe_rlhf.algorithms.registry` (:data:`ALGORITHMS`, :func:`algorithm`): each method as a recipe plus the
  overrides that make it that method; apps (sweeps, compare, the command line) look methods up here;
- :mod:`~pe_rlhf.algorithms.names`: the registry's constants, importing nothing;
- :mod:`pe_rlhf.algorithms.baselines`: SAC and PPO (reward-shaped or Lagrangian), CPO, BC, CQL, GAIL, HG-DAgger, IWR;
- :mod:`pe_rlhf.algorithms.proxy_q`: the reward-free proxy-Q learner of PE-RLHF, HACO and HAIM-DRL.

This ``__init__`` imports only :mod:`~pe_rlhf.algorithms.names`: the registry is imported on first use (it reads the
baselines' table, which imports torch), so that ``from pe_rlhf.algorithms.names import ...`` stays free for a
command line that must start fast, and importing ``pe_rlhf.algorithms.baselines`` or ``pe_rlhf.algorithms.proxy_q``
(which runs this file first) does not import the registry, which imports the baselines back.
"""

from pe_rlhf.algorithms.names import EVALUATE, PROXY_Q, PROXY_Q_RECIPES

_REGISTRY_NAMES = ("ALGORITHMS", "Algorithm", "algorithm", "recipe_names")


def __getattr__(name: str):
    if name in _REGISTRY_NAMES:
        from pe_rlhf.algorithms import registry

        return getattr(registry, name)
    raise AttributeError(f"module 'pe_rlhf.algorithms' has no attribute {name!r}")


__all__ = ["ALGORITHMS", "EVALUATE", "PROXY_Q", "PROXY_Q_RECIPES", "Algorithm", "algorithm", "recipe_names"]
