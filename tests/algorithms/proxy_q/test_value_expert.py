"""The selector's value source: a frozen expert's critics (a SAC run, a Q-ensemble file, the packaged expert)."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict

from pe_rlhf.durable import sha256_file
from pe_rlhf.modules import make_actor, make_qvalue, q_ensemble_from_critics
from pe_rlhf.objectives import PERLHFLoss
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.value_expert import (critics_of_run, export_value_expert, load_value_expert,
                                           packaged_expert_path, parse_value_source)

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")


def critic_values(loss: PERLHFLoss, params, obs, act):
    return loss._q("q", params, TensorDict({"observation": obs}, obs.shape[:1]), act)


def test_members_are_the_online_critics_then_their_targets():
    torch.manual_seed(0)
    loss = PERLHFLoss(make_actor(4, 2, (8,)), make_qvalue(4, 2, (8, 8)), make_qvalue(4, 2, (8,)))
    with torch.no_grad():  # targets differ from the online critics, as after training
        for p in loss.target_qvalue_network_params.values(True, True):
            p.add_(0.1)
    ensemble = q_ensemble_from_critics(loss.qvalue_network_params.flatten_keys("."),
                                       loss.target_qvalue_network_params.flatten_keys("."))
    assert ensemble.config == {"obs_dim": 4, "action_dim": 2, "num_members": 4, "hidden": (8, 8)}
    assert not any(p.requires_grad for p in ensemble.parameters())
    obs, act = torch.randn(16, 4), torch.rand(16, 2) * 2 - 1
    with torch.no_grad():
        expected = torch.cat([critic_values(loss, loss.qvalue_network_params, obs, act),
                              critic_values(loss, loss.target_qvalue_network_params, obs, act)])
    torch.testing.assert_close(ensemble.values(obs, act), expected)
    one = q_ensemble_from_critics(loss.qvalue_network_params.flatten_keys("."), max_members=1)
    torch.testing.assert_close(one.values(obs, act), expected[:1])


def test_mismatched_stacks_are_refused():
    a = make_qvalue(4, 2, (8,)).state_dict()
    b = make_qvalue(4, 2, (8, 8)).state_dict()
    stack = lambda sd: {k: v.unsqueeze(0) for k, v in sd.items()}  # noqa: E731
    with pytest.raises(ValueError, match="stack 1 has parameters"):
        q_ensemble_from_critics(stack(a), stack(b))


def test_a_sac_run_folder_is_an_expert_and_exports_with_provenance(sac_run, tmp_path):
    expert = load_value_expert(sac_run, obs_dim=270)
    assert expert.num_members == 4 and expert.obs_dim == 270  # twin Q and its target twin, lane features
    out = tmp_path / "expert.pt"
    record = export_value_expert(sac_run, out, {"command": "python recipes/sac_rs/train.py profile=smoke"})
    assert record["sha256"] == sha256_file(out) and record["members"] == 4
    assert json.loads(out.with_suffix(".json").read_text())["run_config"]["method"] == "sac_rs"
    obs, act = torch.rand(8, 270) * 2 - 1, torch.rand(8, 2) * 2 - 1
    torch.testing.assert_close(load_value_expert(out, 270).values(obs, act), expert.values(obs, act))
    torch.testing.assert_close(load_value_expert(out, 270, max_members=2).values(obs, act),
                               expert.values(obs, act)[:2])
    torch.testing.assert_close(critics_of_run(sac_run / "checkpoints").values(obs, act), expert.values(obs, act))


def test_an_expert_of_another_observation_width_is_refused(sac_run):
    with pytest.raises(ValueError, match="width 270, the env gives 250"):
        load_value_expert(sac_run, obs_dim=250)


def test_a_folder_without_checkpoints_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="no complete checkpoint"):
        load_value_expert(tmp_path, obs_dim=270)


@pytest.mark.parametrize("text, parsed", [("warmup", ("warmup", None)), ("expert", ("expert", None)),
                                          ("expert:/a/b", ("expert", "/a/b"))])
def test_value_sources_parse(text, parsed):
    kind, path = parse_value_source(text)
    assert (kind, None if path is None else str(path)) == parsed


@pytest.mark.parametrize("value, message", [("bogus", "allowed"), ("expert:/no/such/expert.pt", "does not exist")])
def test_bad_value_sources_name_the_field(value, message):
    with pytest.raises(ConfigError, match=rf"selector\.value.*{message}"):
        load_config(overrides=[f"selector.value={value}"])


def test_the_recipe_builds_a_frozen_expert_and_never_fits_it(sac_run):
    cfg = load_config(overrides=["profile=smoke", f"selector.value=expert:{sac_run}"])
    ensemble = builders.build_value_source(cfg)
    assert ensemble.num_members == min(4, cfg.selector.num_members) and not builders.value_is_fitted(cfg)
    assert not any(p.requires_grad for p in ensemble.parameters())
    assert builders.value_is_fitted(load_config(overrides=["selector.value=warmup"]))


def test_the_packaged_expert_matches_its_provenance():
    path = packaged_expert_path()
    record = json.loads(path.with_suffix(".json").read_text())
    assert record["sha256"] == sha256_file(path)
    expert = load_value_expert(None, obs_dim=270)
    assert expert.num_members == record["members"] == 4
    for key in ("command", "seed", "env_steps", "test_success"):
        assert key in record, key
