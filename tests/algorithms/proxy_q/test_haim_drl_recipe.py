"""The HAIM-DRL recipe (``recipes/haim_drl``): its wiring in the builders, and a smoke run end to end."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from _scripts import load_script

from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.transforms import InterventionTransform, TrafficDisturbanceCost

RECIPE_DIR = Path(__file__).resolve().parents[3] / "recipes" / "haim_drl"


def _load_recipe():
    return load_script("recipes/haim_drl/train.py", "haim_drl_recipe")


def test_builders_add_the_transform_after_the_takeover_and_a_disturbance_critic():
    cfg = load_config(RECIPE_DIR / "config.yaml", ["profile=smoke", "disturbance.threshold=4.5"])
    env = builders.make_worker_env(cfg, worker_index=0, num_workers=1)  # a worker's env, as multisync builds it
    transforms = list(env.transform)
    kinds = [type(t) for t in transforms]
    assert kinds.index(InterventionTransform) < kinds.index(TrafficDisturbanceCost)  # it reads the takeover flag
    assert transforms[kinds.index(TrafficDisturbanceCost)].threshold == 4.5
    assert transforms[kinds.index(InterventionTransform)].selector is None  # HACO's takeover: no physics
    td = env.rollout(3)
    assert td["next", "disturbance_cost"].shape == (3, 1)
    env.close()
    loss, _ = builders.build_loss(cfg, builders.build_actor(cfg))
    assert loss.has_disturbance_critic and loss.disturbance_weight == 1.0
    assert "disturbance_qvalue" in builders.build_optimizers(cfg, loss)
    pe_rlhf = load_config(overrides=["profile=smoke", "loss.objective=paper"])  # the paper's loss, no disturbance
    env = builders.build_train_env(pe_rlhf, driving_config(pe_rlhf), build_mentor(pe_rlhf),
                                   builders.build_value_source(pe_rlhf), builders.build_physics(pe_rlhf))
    assert not any(isinstance(t, TrafficDisturbanceCost) for t in env.transform)
    env.close()
    loss, _ = builders.build_loss(pe_rlhf, builders.build_actor(pe_rlhf))
    assert not loss.has_disturbance_critic and "disturbance_qvalue" not in builders.build_optimizers(pe_rlhf, loss)


def test_smoke_run_writes_every_output(tmp_path):
    # no GIF (about 45% of a smoke run's CPU; the writer is the runtime's: test_training_smoke films a run)
    final = _load_recipe().main(["profile=smoke", "--out", str(tmp_path)])
    for name in ("config.yaml", "metrics.csv", "final_eval.json", "training_curves.png", "actor.safetensors"):
        assert (tmp_path / name).exists(), name
    saved = load_config(tmp_path / "config.yaml", apply_profile=False)
    assert saved.disturbance.enabled and not saved.physics.enabled
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 300 // 50
    for row in rows:
        for key, value in row.items():
            if value != "":
                assert math.isfinite(float(value)), key
        assert float(row["train/disturbance_cost"]) >= 0.0  # logged every batch (0 in warm-up: the mentor drives)
    assert float(rows[0]["train/disturbance_cost"]) == 0.0
    assert any(r.get("loss/disturbance_qvalue") for r in rows[1:])  # its critic was updated
    assert any(r.get("train/q_disturbance") for r in rows[1:])
    assert json.loads((tmp_path / "final_eval.json").read_text())["episodes"] == 1
    assert final["training"]["frames"] == 300
