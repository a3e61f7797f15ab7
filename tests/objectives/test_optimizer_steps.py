"""``make_adam`` and ``ForeachSoftUpdate``: the learners' optimiser and target steps in fewer kernel launches,
with the values of torch's Adam and TorchRL's ``SoftUpdate``."""

from __future__ import annotations

import copy

import pytest
import torch
from torchrl.objectives import SoftUpdate

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import ForeachSoftUpdate, PERLHFLoss, make_adam

OBS = 12


def small_loss(seed: int = 0) -> PERLHFLoss:
    torch.manual_seed(seed)
    return PERLHFLoss(make_actor(OBS, hidden=(16, 16)), make_qvalue(OBS, hidden=(16, 16)),
                      make_qvalue(OBS, hidden=(16, 16)), num_qvalue_nets=2, action_dim=2)


def jiggle(loss: PERLHFLoss, seed: int) -> None:
    """Moves every trainable parameter by a seeded amount (as an optimiser step would)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in loss.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.1)


def targets(loss: PERLHFLoss) -> dict[str, torch.Tensor]:
    return {f"{name}/{'.'.join(k)}": v.clone()
            for name in ("target_qvalue_network_params", "target_intervention_qvalue_network_params")
            for k, v in getattr(loss, name).items(include_nested=True, leaves_only=True)}


def test_foreach_soft_update_moves_the_targets_bit_for_bit_as_torchrl():
    reference, fast = small_loss(), small_loss()
    updaters = SoftUpdate(reference, tau=0.05), ForeachSoftUpdate(fast, tau=0.05)
    before = targets(fast)
    for step in range(5):
        for loss, updater in zip((reference, fast), updaters):
            jiggle(loss, seed=step)
            updater.step()
    after_reference, after_fast = targets(reference), targets(fast)
    assert after_reference.keys() == after_fast.keys() and len(after_fast) == 12  # 2 critics x 3 layers x (W, b)
    for key in after_fast:
        assert torch.equal(after_reference[key], after_fast[key]), key
        assert not torch.equal(before[key], after_fast[key]), key  # the targets did move


def test_foreach_soft_update_is_the_polyak_average():
    loss = small_loss()
    updater = ForeachSoftUpdate(loss, tau=0.25)
    source = {k: v.detach().clone() for k, v in loss.qvalue_network_params.items(True, True)}
    with torch.no_grad():
        for v in loss.target_qvalue_network_params.values(True, True):
            v.zero_()
    updater.step()
    for k, v in loss.target_qvalue_network_params.items(True, True):
        torch.testing.assert_close(v, 0.25 * source[k])


def test_make_adam_is_fused_on_cpu_floats_and_follows_torch_adam():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(8, 32), torch.nn.ReLU(), torch.nn.Linear(32, 1))
    twin = copy.deepcopy(model)
    fast, reference = make_adam(model.parameters(), lr=1e-2), torch.optim.Adam(twin.parameters(), lr=1e-2)
    assert fast.param_groups[0]["fused"] is True and not reference.param_groups[0]["fused"]
    x, y = torch.randn(64, 8), torch.randn(64, 1)
    initial = float(torch.nn.functional.mse_loss(model(x), y))
    for _ in range(50):
        for net, opt in ((model, fast), (twin, reference)):
            opt.zero_grad()
            torch.nn.functional.mse_loss(net(x), y).backward()
            opt.step()
    for p, q in zip(model.parameters(), twin.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
    assert float(torch.nn.functional.mse_loss(model(x), y)) < 0.9 * initial  # it trains


@pytest.mark.parametrize("params", [[torch.zeros(3, dtype=torch.float64, requires_grad=True)],
                                    [torch.zeros(3, device="meta", requires_grad=True)]])
def test_make_adam_falls_back_where_no_fused_kernel_is_asked_for(params):
    opt = make_adam(params, lr=1e-3)
    expected = params[0].device.type != "meta"  # float64 on the CPU has a fused kernel; meta has none
    assert bool(opt.param_groups[0]["fused"]) is expected


def test_the_recipe_learner_uses_them():
    from pe_rlhf.algorithms.proxy_q.builders import build_actor, build_loss, build_optimizers
    from pe_rlhf.algorithms.proxy_q.config import load_config

    cfg = load_config(None, ["profile=smoke"])
    loss, soft_update = build_loss(cfg, build_actor(cfg))
    assert isinstance(soft_update, ForeachSoftUpdate)
    assert all(opt.param_groups[0]["fused"] for opt in build_optimizers(cfg, loss).values())
