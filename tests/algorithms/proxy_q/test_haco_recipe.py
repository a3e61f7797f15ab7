"""The HACO recipe (``recipes/haco``): the PE-RLHF recipe's loop without physics and selector, with the paper's loss,
as the sweeps' ``haco``."""

from __future__ import annotations

import json
from pathlib import Path

from _scripts import load_script

from pe_rlhf.runtime.config import driving_config, to_container
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config, method_name
from pe_rlhf.transforms import InterventionTransform

RECIPE_DIR = Path(__file__).resolve().parents[3] / "recipes" / "haco"


def test_the_recipe_is_the_sweeps_haco_and_builds_no_selector():
    from pe_rlhf.apps.sweeps.methods import builtin_methods

    recipe = load_config(RECIPE_DIR / "config.yaml", ["profile=cpu", "seed=3"])
    assert builtin_methods()["haco"].recipe == "haco" and not builtin_methods()["haco"].overrides
    assert method_name(recipe) == "HACO"
    # the PE-RLHF recipe's config with physics off and the learner as the paper has it (issue 41 changed PE-RLHF's)
    paper_learner = ["physics.enabled=false", "loss.objective=paper", "replay_buffer.takeover_share=null",
                     "actor_selection.every_frames=0"]
    assert to_container(recipe) == to_container(load_config(None, ["profile=cpu", "seed=3", *paper_learner]))
    env = builders.build_train_env(recipe, driving_config(recipe), build_mentor(recipe),
                                   builders.build_value_source(recipe), builders.build_physics(recipe))
    intervention = builders.find_transform(env, InterventionTransform)
    assert intervention.selector is None and intervention.physics is None
    env.close()


def test_smoke_run_executes_only_the_mentor_in_takeovers(tmp_path):
    # no GIF (a third of a smoke run's CPU): test_training_smoke and the HAIM-DRL smoke run check the video
    final = load_script("recipes/haco/train.py", "haco_recipe").main(["profile=smoke", "eval.video=false",
                                                                      "--out", str(tmp_path)])
    saved = load_config(tmp_path / "config.yaml", apply_profile=False)
    assert not saved.physics.enabled
    written = json.loads((tmp_path / "final_eval.json").read_text())
    assert written["success_rate"] == final["success_rate"]
    assert (tmp_path / "actor.safetensors").is_file()
