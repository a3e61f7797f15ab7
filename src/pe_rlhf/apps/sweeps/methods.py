"""Methods a sweep can run: each is a recipe entry plus the overrides that make it that method.

A :class:`MethodSpec` says which entry point runs a cell (``pe_rlhf`` / ``haco`` / ``haim_drl``: the proxy-Q recipe
:func:`pe_rlhf.algorithms.proxy_q.recipe.main` with that recipe's ``config.yaml``; a baseline name such as ``sac_rs``:
:func:`pe_rlhf.algorithms.baselines.main`; ``evaluate``: no training, the registered ``policy`` is evaluated on the
recipe's test scenes), the overrides that turn the recipe into the method (HACO = PE-RLHF without physics
and selector), which config key the sweep's mentor axis sets (None: the method has no mentor, the axis
does not apply) and whether the sweep's parameter axis applies.
"""

from __future__ import annotations

from dataclasses import dataclass

from pe_rlhf.algorithms.names import EVALUATE, PROXY_Q_RECIPES


def proxy_q_config_path(recipe: str):
    """The config file of a proxy-Q recipe: None for ``pe_rlhf`` (the built-in defaults, equal to
    ``recipes/pe_rlhf/config.yaml``), else ``recipes/<recipe>/config.yaml``."""
    from pe_rlhf.algorithms.baselines.config import recipe_config_path

    return None if recipe == "pe_rlhf" else recipe_config_path(recipe)


@dataclass(frozen=True)
class MethodSpec:
    """``name`` (the row label and cell-name prefix), ``recipe`` (``pe_rlhf``, ``haim_drl``, a
    :data:`pe_rlhf.algorithms.baselines.METHODS` key, or ``evaluate``), ``overrides`` (recipe config ``key=value``),
    ``policy`` (``evaluate`` only: a registered evaluation policy), ``mentor_key`` (the config key the
    mentor axis sets; None: no mentor) and ``parameters`` (False: the parameter axis does not apply)."""

    name: str
    recipe: str
    overrides: tuple[str, ...] = ()
    policy: str | None = None
    mentor_key: str | None = "mentor.name"
    parameters: bool = True

    @property
    def trains(self) -> bool:
        return self.recipe != EVALUATE


def builtin_methods() -> dict[str, MethodSpec]:
    """The methods a sweep config may name without defining them: one per entry of
    :data:`pe_rlhf.algorithms.ALGORITHMS`, the one registry."""
    from pe_rlhf.algorithms import ALGORITHMS

    return {name: MethodSpec(name, a.recipe, a.overrides, policy=a.policy, mentor_key=a.mentor_key,
                             parameters=a.trains)
            for name, a in ALGORITHMS.items()}


def recipe_names() -> tuple[str, ...]:
    from pe_rlhf.algorithms import recipe_names as registered

    return registered()
