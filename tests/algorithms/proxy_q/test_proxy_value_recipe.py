"""``loss.objective=proxy_value`` in the proxy-Q recipes and the PVP recipe (``recipes/pvp``): the builders' objects,
the collection noise, the method's name, and a smoke run whose saved actor loads back."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import torch
from _scripts import load_script
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from pe_rlhf.algorithms import algorithm
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import algorithm_name, load_config, method_name
from pe_rlhf.algorithms.proxy_q.trained_policy import load_run_actor
from pe_rlhf.objectives import PERLHFLoss, ProxyValueLoss
from pe_rlhf.runtime.config_rules import ConfigError

PVP_DIR = Path(__file__).resolve().parents[3] / "recipes" / "pvp"


def test_proxy_value_objective_builds_a_deterministic_actor_its_loss_and_two_optimizers():
    cfg = load_config(overrides=["profile=smoke", "loss.objective=proxy_value", "loss.layer_norm=true",
                                 "loss.q_value_bound=2", "loss.bc_weight=0.5", "loss.policy_delay=3"])
    actor = builders.build_actor(cfg)
    assert not isinstance(actor, ProbabilisticActor) and actor.out_keys == ["action"]
    loss, _ = builders.build_loss(cfg, actor)
    assert isinstance(loss, ProxyValueLoss)
    assert (loss.q_value_bound, loss.bc_weight, loss.policy_delay) == (2.0, 0.5, 3)
    assert any(isinstance(m, torch.nn.LayerNorm) for m in loss.qvalue_network.modules())
    assert set(builders.build_optimizers(cfg, loss)) == {"actor", "qvalue"}
    assert method_name(cfg) == "PE-RLHF"  # the physics-enhanced takeover composes with it unchanged
    default = load_config(overrides=["profile=smoke"])  # PE-RLHF's default since issue 41: the proxy values
    assert default.loss.objective == "proxy_value"
    assert isinstance(builders.build_loss(default, builders.build_actor(default))[0], ProxyValueLoss)
    paper = load_config(overrides=["profile=smoke", "loss.objective=paper"])  # the paper's loss (recipes/haco)
    actor = builders.build_actor(paper)
    assert isinstance(actor, ProbabilisticActor) and isinstance(builders.build_loss(paper, actor)[0], PERLHFLoss)


def test_exploration_noise_perturbs_collection_only():
    cfg = load_config(overrides=["profile=smoke", "loss.objective=proxy_value", "collector.exploration_noise=0.3"])
    torch.manual_seed(0)
    actor = builders.build_actor(cfg)
    policy = builders.build_collection_policy(cfg, actor)
    td = TensorDict({"observation": torch.randn(64, cfg_obs(cfg))}, [64])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        clean = actor(td.clone())["action"]
        assert torch.equal(policy(td.clone())["action"], clean)
    with set_exploration_type(ExplorationType.RANDOM):
        noisy = policy(td.clone())["action"]
    spread = (noisy - clean).std().item()
    assert 0.15 < spread < 0.4 and noisy.abs().max() <= 1.0
    quiet = load_config(overrides=["profile=smoke", "loss.objective=proxy_value"])
    assert builders.build_collection_policy(quiet, actor) is actor


def cfg_obs(cfg) -> int:
    from pe_rlhf.runtime.world import obs_dim

    return obs_dim(cfg)


def test_pvp_recipe_is_the_registry_method_and_refuses_a_disturbance_critic():
    cfg = load_config(PVP_DIR / "config.yaml", ["profile=smoke"])
    assert (method_name(cfg), algorithm_name(cfg)) == ("PVP", "pvp")
    assert cfg.loss.objective == "proxy_value" and cfg.replay_buffer.takeover_share == 0.5
    assert algorithm("pvp").recipe == "pvp"
    with pytest.raises(ConfigError, match="disturbance.enabled"):
        load_config(PVP_DIR / "config.yaml", ["profile=smoke", "disturbance.enabled=true"])


def test_pvp_smoke_run_learns_from_proxy_values_and_its_actor_loads_back(tmp_path):
    # no GIF (a third of a smoke run's CPU): test_training_smoke and the HAIM-DRL smoke run check the video
    final = load_script("recipes/pvp/train.py", "pvp_recipe").main(["profile=smoke", "eval.video=false",
                                                                    "--out", str(tmp_path)])
    assert json.loads((tmp_path / "final_eval.json").read_text())["algorithm"] == "pvp"
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    proxy = [float(r["train/proxy_loss"]) for r in rows if r.get("train/proxy_loss")]
    assert proxy and all(p >= 0 for p in proxy)
    # the labels pull the executed action's value up and the proposal's down on takeover rows
    last = rows[-1]
    assert float(last["train/q_behavior"]) > float(last["train/q_agent"])
    actor = load_run_actor(tmp_path)
    assert not isinstance(actor, ProbabilisticActor)
    assert final["episodes"] >= 1
