"""A user's mentor class given as ``package.module:Name`` (examples/cautious_mentor.py) drives the recipe."""

import sys
from pathlib import Path

import numpy as np
import pytest

from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.algorithms.proxy_q.config import load_config

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def examples_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLES))
    yield
    sys.modules.pop("cautious_mentor", None)


def test_import_path_mentor_takes_over_by_its_own_rule(examples_on_path):
    from pe_rlhf.envs import make_gym_env

    cfg = load_config(overrides=["profile=smoke", "mentor.name=cautious_mentor:CautiousMentor"])
    mentor = build_mentor(cfg)
    assert type(mentor).__name__ == "CautiousMentor"
    env = make_gym_env({"split": None, "horizon": 50})
    env.reset(options={"scene_seed": 1000})
    mentor.reset(env)
    own = mentor.act(env)
    assert mentor(env, own) == (False, pytest.approx(own))  # its own action: no takeover
    far = np.clip(own + np.array([0.0, 0.9], dtype=np.float32), -1, 1)
    if abs(far[1] - own[1]) <= 0.5:
        far[1] = -1.0 if own[1] > 0 else 1.0
    takeover, action = mentor(env, far)
    assert takeover and np.allclose(action, own)


def test_a_class_that_is_not_a_mentor_is_refused(examples_on_path):
    cfg = load_config(overrides=["profile=smoke", "mentor.name=cautious_mentor:IDMMobilPolicy"])
    with pytest.raises(TypeError, match="not a pe_rlhf Mentor"):
        build_mentor(cfg)


def test_malformed_import_path_fails_at_config_time():
    with pytest.raises(ConfigError, match="mentor.name"):
        load_config(overrides=["mentor.name=not a path"])
