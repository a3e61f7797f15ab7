"""The one registry of training methods: every name a sweep, a comparison or a user may give.

An :class:`Algorithm` says which recipe runs it (its ``recipes/<recipe>/config.yaml`` is the method's default
config; ``evaluate``: no training, a registered evaluation policy is scored), the ``key=value`` overrides that
turn the recipe into the method (HACO = the PE-RLHF recipe without physics and selector), its family, its
display name, and which config key a mentor is set with (None: the method has no mentor).

Families:
- ``proxy_q``: the reward-free proxy-Q learners (PE-RLHF, HACO, HAIM-DRL, PVP), run by
  :func:`pe_rlhf.algorithms.proxy_q.recipe.main`;
- ``sac``, ``ppo``, ``cpo``: reward-trained RL baselines, ``offline`` (BC, CQL), ``gail``, ``hil`` (HG-DAgger, IWR),
  run by :func:`pe_rlhf.algorithms.baselines.main`;
- ``evaluate``: a fixed policy (IDM-MOBIL), scored on the recipe's test scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

from pe_rlhf.algorithms.names import EVALUATE, PROXY_Q, PROXY_Q_RECIPES
from pe_rlhf.algorithms.baselines.config import METHODS as BASELINE_METHODS
from pe_rlhf.algorithms.baselines.config import algorithm_name as baseline_algorithm_name


@dataclass(frozen=True)
class Algorithm:
    """``name`` (the registry key, a sweep's row label and cell-name prefix), ``display`` (the table label),
    ``family`` (see the module docstring), ``recipe`` (the entry point and default config: ``pe_rlhf``,
    ``haco``, ``haim_drl``, a baseline such as ``sac_rs``, or ``evaluate``), ``overrides`` (recipe config
    ``key=value``), ``policy`` (``evaluate`` only: a registered evaluation policy) and ``mentor_key`` (the config
    key a mentor is set with; None: no mentor)."""

    name: str
    display: str
    family: str
    recipe: str
    overrides: tuple[str, ...] = ()
    policy: str | None = None
    mentor_key: str | None = "mentor.name"

    @property
    def trains(self) -> bool:
        return self.family != EVALUATE


def _baseline(key: str) -> Algorithm:
    method = BASELINE_METHODS[key]
    if method.family == "hil":
        mentor_key = "mentor.name"
    elif method.family in ("offline", "gail"):
        mentor_key = "data.mentor"  # the demonstrations' driver
    else:
        mentor_key = None
    return Algorithm(baseline_algorithm_name(key), method.name, method.family, key, mentor_key=mentor_key)


ALGORITHMS: dict[str, Algorithm] = {
    algorithm.name: algorithm
    for algorithm in (
        Algorithm("pe-rlhf", "PE-RLHF", PROXY_Q, "pe_rlhf"),
        Algorithm("haco", "HACO", PROXY_Q, "haco"),
        Algorithm("haim-drl", "HAIM-DRL", PROXY_Q, "haim_drl"),
        Algorithm("pvp", "PVP", PROXY_Q, "pvp"),
        Algorithm("idm-mobil", "IDM-MOBIL", EVALUATE, EVALUATE, policy="idm-mobil", mentor_key=None),
        *(_baseline(key) for key in BASELINE_METHODS),
    )
}


def algorithm(name: str) -> Algorithm:
    """The registered algorithm ``name``; a ``ValueError`` naming the allowed ones otherwise."""
    try:
        return ALGORITHMS[name]
    except (KeyError, TypeError):
        raise ValueError(f"algorithm {name!r} is not registered; allowed: {list(ALGORITHMS)}") from None


def recipe_names() -> tuple[str, ...]:
    """Every recipe an algorithm may run: the proxy-Q recipes, the baselines and ``evaluate``."""
    return (*PROXY_Q_RECIPES, *BASELINE_METHODS, EVALUATE)
