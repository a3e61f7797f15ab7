"""Tests of ``optim.precision`` (:mod:`pe_rlhf.modules.precision`): bf16 autocast in the updates with
fp32 weights and fp32 network outputs.

Known answers: outside autocast ``Float32Linear`` is ``nn.Linear`` bit for bit and the networks'
initial weights do not change; inside, hidden activations are bf16 and outputs fp32; one SAC update
in bf16 lands within bf16's rounding of the fp32 update; a bf16 SAC learns the bandit
``r = -(a - 0.5)^2`` (optimum 0.5) as well as fp32 does; the recipes' configs take the field and
name it when it is wrong.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP
from torchrl.objectives import SACLoss, SoftUpdate

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.modules.precision import Float32Linear, fp32_output_layer, update_precision
from pe_rlhf.runtime.update import update

pytestmark = [pytest.mark.usefixtures("one_thread_module")]


def test_float32_linear_equals_linear_outside_autocast_and_stays_fp32_inside():
    torch.manual_seed(0)
    plain = nn.Linear(8, 3)
    torch.manual_seed(0)
    exempt = Float32Linear(8, 3)
    x = torch.randn(5, 8)
    assert torch.equal(plain(x), exempt(x))
    with update_precision("bf16"):
        assert plain(x).dtype == torch.bfloat16  # what autocast does to a plain layer
        out = exempt(x.bfloat16())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, plain(x.bfloat16().float()))


def test_fp32_output_layer_keeps_weights_names_and_the_rng_stream():
    torch.manual_seed(3)
    plain = MLP(in_features=6, out_features=2, num_cells=[16, 16])
    after_plain = torch.rand(1)
    torch.manual_seed(3)
    mixed = fp32_output_layer(MLP(in_features=6, out_features=2, num_cells=[16, 16]))
    assert torch.equal(torch.rand(1), after_plain)
    assert plain.state_dict().keys() == mixed.state_dict().keys()
    assert all(torch.equal(a, b) for a, b in zip(plain.state_dict().values(), mixed.state_dict().values()))
    assert [type(m) for m in mixed if isinstance(m, nn.Linear)] == [nn.Linear, nn.Linear, Float32Linear]
    with pytest.raises(ValueError, match="no nn.Linear"):
        fp32_output_layer(nn.Sequential(nn.ReLU()))


def test_networks_output_fp32_under_autocast_with_bf16_hidden_layers():
    critic, actor = make_qvalue(5, 2, (32, 32)), make_actor(5, 2, (32, 32))
    td = TensorDict({"observation": torch.randn(4, 5), "action": torch.rand(4, 2) * 2 - 1}, [4])
    hidden = []
    handle = critic.module.mlp[0].register_forward_hook(lambda m, i, o: hidden.append(o.dtype))
    with update_precision("bf16"):
        q = critic(td.clone())["state_action_value"]
        a = actor(td.clone())
    handle.remove()
    assert hidden == [torch.bfloat16]
    assert q.dtype == a["loc"].dtype == a["scale"].dtype == a["action"].dtype == torch.float32


def test_update_precision_rejects_an_unknown_name():
    with pytest.raises(ValueError, match="allowed"):
        update_precision("fp16")


def _sac(seed: int, obs: int = 4, hidden=(64, 64)):
    torch.manual_seed(seed)
    loss = SACLoss(make_actor(obs, 1, hidden), make_qvalue(obs, 1, hidden), num_qvalue_nets=2, loss_function="l2")
    loss.make_value_estimator(gamma=0.99)
    optimisers = {"all": torch.optim.Adam(loss.parameters(), lr=3e-3)}
    return loss, optimisers, SoftUpdate(loss, tau=0.05)


def _batch(n: int, obs: int, seed: int, reward=None) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    action = torch.rand(n, 1, generator=g) * 2 - 1
    r = reward(action) if reward is not None else torch.randn(n, 1, generator=g) * 10
    done = torch.ones(n, 1, dtype=torch.bool) if reward is not None else torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict({"observation": torch.randn(n, obs, generator=g), "action": action,
                       "next": {"observation": torch.randn(n, obs, generator=g), "reward": r, "done": done,
                                "terminated": done}}, [n])


def test_one_bf16_update_matches_fp32_within_rounding():
    """Same networks, same batch, same actor samples: bf16's losses and gradients are fp32's up to rounding."""
    data = _batch(256, 4, seed=1)
    results, grads = {}, {}
    for precision in ("fp32", "bf16"):
        loss, optimisers, soft = _sac(seed=0)
        torch.manual_seed(7)
        with update_precision(precision):
            out = loss(data)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        results[precision] = {k: float(v.detach()) for k, v in out.items()}
        grads[precision] = torch.cat([p.grad.flatten() for p in loss.parameters() if p.grad is not None])
        assert all(p.dtype == torch.float32 for p in loss.parameters())
    for key in ("loss_qvalue", "loss_actor"):
        assert results["bf16"][key] == pytest.approx(results["fp32"][key], rel=0.03, abs=0.05), key
    g32, g16 = grads["fp32"], grads["bf16"]
    assert torch.nn.functional.cosine_similarity(g32, g16, dim=0) > 0.99
    assert (g16.norm() / g32.norm()).item() == pytest.approx(1.0, abs=0.05)
    # and update() takes its step under the same autocast
    loss, optimisers, soft = _sac(seed=0)
    assert update(loss, optimisers, soft, data, None, "bf16")["loss_qvalue"] == pytest.approx(
        results["bf16"]["loss_qvalue"], rel=0.03)


def test_bf16_sac_learns_a_bandit_as_well_as_fp32():
    """One-step bandit ``r = -(a - 0.5)^2`` (terminal): the deterministic action goes to 0.5."""
    modes = {}
    for precision in ("fp32", "bf16"):
        loss, optimisers, soft = _sac(seed=0, obs=1, hidden=(32, 32))
        loss.log_alpha.data.fill_(-5.0)  # little entropy bonus: the optimum stays at 0.5
        for step in range(300):
            td = _batch(64, 1, seed=step, reward=lambda a: -(a - 0.5) ** 2)
            td["observation"] = td["next", "observation"] = torch.zeros(64, 1)
            update(loss, optimisers, soft, td, None, precision)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            modes[precision] = loss.actor_network(TensorDict({"observation": torch.zeros(1, 1)}, [1]))["action"].item()
    assert modes["fp32"] == pytest.approx(0.5, abs=0.1)
    assert modes["bf16"] == pytest.approx(0.5, abs=0.1)


@pytest.mark.parametrize("loader", ["pe_rlhf", "sac_rs", "sac_lag"])
def test_recipe_configs_take_precision_and_name_a_bad_value(loader):
    from pe_rlhf.algorithms.baselines import load_baseline_config
    from pe_rlhf.runtime.config_rules import ConfigError
    from pe_rlhf.algorithms.proxy_q.config import load_config

    load = ((lambda o: load_config(None, o)) if loader == "pe_rlhf"
            else (lambda o: load_baseline_config(loader, overrides=o)))
    assert load([]).optim.precision == "fp32"
    assert load(["optim.precision=bf16"]).optim.precision == "bf16"
    with pytest.raises(ConfigError, match=r"optim\.precision"):
        load(["optim.precision=fp16"])
