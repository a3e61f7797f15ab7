"""README's "Compose the pieces" builds the method ``recipes/pe_rlhf/train.py`` runs with its defaults: the same
classes with the same settings as the recipe's builders make (env, mentor, physics, selector and its value
source, the intervention transform, ``ProxyValueLoss`` and its networks)."""

from __future__ import annotations

import dataclasses

import pytest
from _doc_blocks import ROOT, read_blocks

from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.objectives import ProxyValueLoss
from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.transforms import InterventionTransform

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore:No target network updater")]

LOSS_SETTINGS = ("q_value_bound", "gamma", "num_qvalue_nets", "target_noise", "target_noise_clip", "policy_delay",
                 "bc_weight", "mask_td_at_takeover_start", "proxy_reduction")
SELECTOR_SETTINGS = ("epsilon_select", "variance_threshold", "persistence", "reference", "strict_in_danger",
                     "progress_margin", "latch_release_speed")


@pytest.fixture(scope="module")
def readme():
    block = next(b for b in read_blocks(ROOT / "README.md") if b.lang == "python")
    namespace: dict = {}
    exec(compile(block.code, block.id, "exec"), namespace)
    return namespace


@pytest.fixture(scope="module")
def recipe():
    cfg = load_config(None, overrides=[])  # recipes/pe_rlhf/config.yaml, as train.py composes it with no override
    env = builders.build_train_env(cfg, driving_config(cfg), build_mentor(cfg), builders.build_value_source(cfg),
                                   builders.build_physics(cfg))
    loss, _ = builders.build_loss(cfg, builders.build_actor(cfg))
    return {"env": env, "loss": loss, "cfg": cfg}


def shapes(params) -> dict:
    return {k: tuple(v.shape) for k, v in params.items(True, True)}


def test_the_env_and_its_transforms_are_the_recipes(readme, recipe):
    mine, theirs = readme["env"], recipe["env"]
    assert [type(t) for t in mine.transform] == [type(t) for t in theirs.transform]
    assert mine.base_env.driving_env.world == theirs.base_env.driving_env.world  # DrivingConfig: lanes, split, traffic
    assert mine.observation_spec["observation"].shape == theirs.observation_spec["observation"].shape == (270,)


def test_the_takeover_is_the_recipes(readme, recipe):
    mine = next(t for t in readme["env"].transform if isinstance(t, InterventionTransform))
    theirs = next(t for t in recipe["env"].transform if isinstance(t, InterventionTransform))
    assert type(mine.mentor) is type(theirs.mentor) and mine.mentor.name == theirs.mentor.name == "professional"
    assert mine.mentor.profile == theirs.mentor.profile and mine.mentor.seed == theirs.mentor.seed
    assert type(mine.physics) is type(theirs.physics) and mine.physics.config == theirs.physics.config
    assert mine.warmup_steps == theirs.warmup_steps == 10_000
    assert mine.core.warmup_selection == theirs.core.warmup_selection and mine.warmup_driver is theirs.warmup_driver
    assert type(mine.selector) is type(theirs.selector)
    for name in SELECTOR_SETTINGS:
        assert getattr(mine.selector, name) == getattr(theirs.selector, name), name
    assert mine.selector.epsilon_select == -0.5  # seconds: the forecast's calibrated threshold
    value, recipe_value = mine.selector.q_ensemble, theirs.selector.q_ensemble
    assert type(value).__name__ == type(recipe_value).__name__ == "SafetyForecastValue"
    assert dataclasses.asdict(value.config) == dataclasses.asdict(recipe_value.config)


def test_the_loss_is_the_recipes(readme, recipe):
    mine, theirs = readme["loss"], recipe["loss"]
    assert type(mine) is type(theirs) is ProxyValueLoss
    for name in LOSS_SETTINGS:
        assert getattr(mine, name) == getattr(theirs, name), name
    for params in ("actor_network_params", "qvalue_network_params"):
        assert shapes(getattr(mine, params)) == shapes(getattr(theirs, params)), params
