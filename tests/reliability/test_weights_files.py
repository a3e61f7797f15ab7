"""Issue 44's bullet, kept here: weights (actors, critics, the packaged expert) are safetensors files; a legacy
``actor.pt`` still loads (``weights_only=True``); a truncated or corrupt file of either kind is one line naming it
and what is wrong.
"""

from __future__ import annotations

import shutil

import pytest
import torch
from _runs import train
from _scripts import ROOT
from safetensors.torch import load_file

from pe_rlhf.algorithms.baselines import load_baseline_actor
from pe_rlhf.algorithms.proxy_q.trained_policy import load_actor
from pe_rlhf.algorithms.proxy_q.value_expert import load_value_expert, packaged_expert_path
from pe_rlhf.modules import load_q_ensemble

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]
LEGACY = ROOT / "docs" / "results" / "claims" / "warmup" / "expert_sac_rs_seed0"


def test_a_run_writes_its_actor_as_safetensors_and_loads_it(tmp_path):
    out = tmp_path / "run"
    train(out, "collector.total_frames=100")
    assert not (out / "actor.pt").exists()
    saved = load_file(out / "actor.safetensors")
    actor = load_actor(out)
    assert {k: torch.equal(v, saved[k]) for k, v in actor.state_dict().items()} == dict.fromkeys(saved, True)
    truncated = tmp_path / "truncated"
    shutil.copytree(out, truncated)
    data = (truncated / "actor.safetensors").read_bytes()
    (truncated / "actor.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError) as refused:
        load_actor(truncated)
    message = str(refused.value)
    assert message.startswith(f"refusing {truncated / 'actor.safetensors'}: not a readable safetensors file")
    assert "\n" not in message and len(message) < 400


def test_a_legacy_actor_pt_of_an_existing_run_folder_still_loads():
    assert (LEGACY / "actor.pt").is_file() and not (LEGACY / "actor.safetensors").exists()
    actor = load_baseline_actor(LEGACY)
    legacy = torch.load(LEGACY / "actor.pt", weights_only=True)
    assert all(torch.equal(v, legacy[k]) for k, v in actor.state_dict().items())


def test_the_packaged_expert_is_safetensors_and_a_damaged_copy_is_one_line(tmp_path):
    path = packaged_expert_path()
    assert path.name == "value_expert.safetensors" and path.read_bytes()[:2] != b"PK"
    expert = load_value_expert(None, 270)
    assert expert.num_members == 4 and expert.obs_dim == 270
    damaged = tmp_path / "value_expert.safetensors"
    damaged.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ValueError) as refused:
        load_q_ensemble(damaged)
    assert str(damaged) in str(refused.value) and "\n" not in str(refused.value)
    assert "not a readable safetensors file" in str(refused.value)
