"""The one algorithm registry: every method a sweep may name comes from it, each entry's recipe exists, and
its overrides make the recipe the method it names."""

from __future__ import annotations

from pathlib import Path

import pytest

from pe_rlhf.algorithms import ALGORITHMS, EVALUATE, PROXY_Q, algorithm, recipe_names
from pe_rlhf.algorithms.baselines import METHODS
from pe_rlhf.apps.sweeps.methods import builtin_methods

RECIPES = Path(__file__).resolve().parents[2] / "recipes"


def test_every_algorithm_has_its_recipe_config():
    for name, entry in ALGORITHMS.items():
        assert entry.name == name
        assert entry.recipe in recipe_names()
        if entry.trains:
            assert (RECIPES / entry.recipe / "config.yaml").is_file(), name
        else:
            assert entry.recipe == EVALUATE and entry.policy and entry.mentor_key is None


def test_display_names_are_unique_and_baselines_keep_theirs():
    displays = [a.display for a in ALGORITHMS.values()]
    assert len(set(displays)) == len(displays)
    for key, method in METHODS.items():
        entry = ALGORITHMS[key.replace("_", "-")]
        assert (entry.display, entry.family, entry.recipe) == (method.name, method.family, key)


def test_sweeps_name_exactly_the_registered_methods():
    methods = builtin_methods()
    assert list(methods) == list(ALGORITHMS)
    for name, spec in methods.items():
        entry = ALGORITHMS[name]
        assert (spec.recipe, spec.overrides, spec.policy, spec.mentor_key) == (
            entry.recipe, entry.overrides, entry.policy, entry.mentor_key)
        assert spec.parameters == entry.trains


@pytest.mark.parametrize("name, expected", [("pe-rlhf", "PE-RLHF"), ("haco", "HACO"), ("haim-drl", "HAIM-DRL")])
def test_proxy_q_overrides_make_the_method_they_name(name, expected):
    from pe_rlhf.algorithms.proxy_q.config import load_config, method_name

    entry = algorithm(name)
    assert entry.family == PROXY_Q and entry.display == expected
    config = None if entry.recipe == "pe_rlhf" else RECIPES / entry.recipe / "config.yaml"
    assert method_name(load_config(config, ["profile=smoke", *entry.overrides])) == expected


def test_the_name_a_run_records_is_its_registry_name():
    """What a run folder records (``algorithm``) is the key it is registered under, for every training method."""
    from pe_rlhf.algorithms.baselines.config import algorithm_name as baseline_name
    from pe_rlhf.algorithms.proxy_q.config import PROXY_Q_ALGORITHMS, algorithm_name, load_config

    proxy_q = [a for a in ALGORITHMS.values() if a.family == PROXY_Q]
    assert tuple(a.name for a in proxy_q) == PROXY_Q_ALGORITHMS
    for entry in proxy_q:
        config = None if entry.recipe == "pe_rlhf" else RECIPES / entry.recipe / "config.yaml"
        assert algorithm_name(load_config(config, ["profile=smoke", *entry.overrides])) == entry.name
    for key in METHODS:
        assert ALGORITHMS[baseline_name(key)].recipe == key


def test_an_unknown_name_is_one_line_naming_the_allowed():
    with pytest.raises(ValueError, match=r"'ppo' is not registered; allowed: \['pe-rlhf', 'haco'"):
        algorithm("ppo")
