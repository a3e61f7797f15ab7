"""``PERLHFLoss(fused_critics=True)`` (the default) against the module path (``fused_critics=False``).

The fused path evaluates ``make_qvalue`` critics from their stacked parameters and computes each state's
first-layer product once for all the actions it is valued at (``pe_rlhf.objectives.fused_critics``). It must
give the module path's losses, diagnostics and gradients up to the order of a float sum: 1e-5 relative here
(each gradient relative to its largest entry), on a random batch whose shapes are checked by hand.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import PERLHFLoss
from pe_rlhf.objectives.fused_critics import evaluate, mlp_plan, project_state
from pe_rlhf.objectives.perlhf import make_transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")

OBS_DIM, ACTION_DIM, HIDDEN, BATCH = 10, 2, (32, 32), 64
RTOL = 1e-5


def random_batch(batch: int = BATCH, takeover_rate: float = 0.25, seed: int = 1) -> TensorDict:
    """Random observations and actions, ``takeover_rate`` takeover rows (a third of them starts), 10% terminal
    rows, half of those successes, a random reward and disturbance cost."""
    g = torch.Generator().manual_seed(seed)
    agent = torch.rand(batch, ACTION_DIM, generator=g) * 2 - 1
    takeover = torch.rand(batch, 1, generator=g) < takeover_rate
    behavior = torch.where(takeover, torch.rand(batch, ACTION_DIM, generator=g) * 2 - 1, agent)
    start = takeover & (torch.rand(batch, 1, generator=g) < 1 / 3)
    terminated = torch.rand(batch, 1, generator=g) < 0.1
    td = make_transitions(torch.randn(batch, OBS_DIM, generator=g), torch.randn(batch, OBS_DIM, generator=g),
                          agent, behavior, takeover, start, terminated, torch.randn(batch, 1, generator=g),
                          disturbance_cost=torch.rand(batch, 1, generator=g))
    td.set(("next", "success"), terminated & (torch.rand(batch, 1, generator=g) < 0.5))
    return td


def make_loss(fused: bool, disturbance: bool = False, **kwargs) -> PERLHFLoss:
    torch.manual_seed(0)
    networks = [make_actor(OBS_DIM, ACTION_DIM, HIDDEN), make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN),
                make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN)]
    if disturbance:
        networks.append(make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN))
    return PERLHFLoss(*networks, fused_critics=fused, **kwargs)


def loss_and_grads(loss: PERLHFLoss, batch: TensorDict) -> tuple[TensorDict, dict[str, torch.Tensor]]:
    torch.manual_seed(123)  # the same actor samples in both paths
    out = loss(batch.clone())
    loss.zero_grad(set_to_none=True)
    sum(value for key, value in out.items() if key.startswith("loss_")).backward()
    return out.detach(), {name: p.grad.clone() for name, p in loss.named_parameters() if p.grad is not None}


def assert_close(actual: torch.Tensor, expected: torch.Tensor, what: str) -> None:
    scale = float(expected.detach().abs().max()) if expected.numel() else 0.0
    torch.testing.assert_close(actual, expected, rtol=RTOL, atol=RTOL * scale + 1e-12, msg=what)


VARIANTS = {
    "default": {},
    "twin_q_int": {"num_intervention_qvalue_nets": 2},
    "zero_target_three_q": {"failure_target": "zero", "num_qvalue_nets": 3},
    "batch_min_reward": {"failure_target": "batch_min", "use_reward": True},
    "bootstrap_no_cosine": {"failure_target": "bootstrap", "cosine_cost": False},
    "disturbance": {"disturbance": True},
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("takeover_rate", [0.25, 0.0])
def test_fused_path_gives_the_module_paths_losses_and_gradients(variant, takeover_rate):
    batch = random_batch(takeover_rate=takeover_rate)
    modules, fused = make_loss(False, **VARIANTS[variant]), make_loss(True, **VARIANTS[variant])
    assert fused._fusable("q", batch) and not modules._fusable("q", batch)
    expected, expected_grads = loss_and_grads(modules, batch)
    actual, grads = loss_and_grads(fused, batch)
    assert set(actual.keys()) == set(expected.keys())
    for key in expected.keys():  # noqa: SIM118 (iterating a TensorDict walks its batch dim, not its keys)
        assert_close(actual[key], expected[key], key)
    assert set(grads) == set(expected_grads)
    for name, grad in expected_grads.items():
        assert_close(grads[name], grad, name)


def test_critic_values_have_the_hand_checked_shapes_in_both_paths():
    """Rows: B for targets, the intervention critic and the actor's values; B + n_takeover for the proxy-Q
    (executed action on every row, then the agent's on the takeover rows). Copies lead."""
    batch = random_batch()
    n_takeover = int(batch["next", "intervention"].sum())
    assert 0 < n_takeover < BATCH
    takeover = batch["next", "intervention"].squeeze(-1).nonzero().squeeze(-1)
    expected = {"next_q": (2, BATCH), "q": (2, BATCH + n_takeover), "q_new": (2, BATCH),
                "next_q_int": (1, BATCH), "q_int": (1, BATCH), "q_int_new": (1, BATCH),
                "next_q_dist": (2, BATCH), "q_dist": (2, BATCH), "q_dist_new": (2, BATCH)}
    values = {}
    for fused in (False, True):
        loss = make_loss(fused, disturbance=True)
        torch.manual_seed(5)
        next_action = torch.rand(BATCH, ACTION_DIM) * 2 - 1
        new_action = (torch.rand(BATCH, ACTION_DIM) * 2 - 1).requires_grad_()
        values[fused] = loss._critic_values(batch, batch["next"], next_action, new_action, takeover)
        assert {key: tuple(v.shape) for key, v in values[fused].items()} == expected
        assert values[fused]["q_new"].requires_grad and not values[fused]["next_q"].requires_grad
    for key in expected:
        assert_close(values[True][key], values[False][key], key)


def test_project_and_evaluate_equal_the_module_on_each_copy():
    torch.manual_seed(0)
    critic = make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN)
    plan = mlp_plan(critic)
    params = TensorDict.from_module(critic).expand(3).clone()  # three copies, made different below
    params.apply_(lambda p: p.add_(torch.randn_like(p)))
    obs, action = torch.randn(7, OBS_DIM), torch.rand(7, ACTION_DIM)
    state_part = project_state(obs, plan.read(params))
    assert state_part.shape == (3, 7, HIDDEN[0])
    values = evaluate(plan.read(params), state_part, action)
    assert values.shape == (3, 7)
    for k in range(3):
        with params[k].to_module(critic):
            expected = critic(TensorDict({"observation": obs, "action": action}, [7]))["state_action_value"]
        assert_close(values[k], expected.squeeze(-1), f"copy {k}")


class ConstantQ(nn.Module):
    def __init__(self):
        super().__init__()
        self.value = nn.Parameter(torch.zeros(()))

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.value.expand(*observation.shape[:-1], 1)


def test_only_recognised_critics_on_a_flat_batch_outside_autocast_are_fused():
    batch = random_batch()
    custom = TensorDictModule(ConstantQ(), in_keys=["observation", "action"], out_keys=["state_action_value"])
    assert mlp_plan(custom) is None
    torch.manual_seed(0)
    loss = PERLHFLoss(make_actor(OBS_DIM, ACTION_DIM, HIDDEN), make_qvalue(OBS_DIM, ACTION_DIM, HIDDEN), custom)
    assert loss._fusable("q", batch) and not loss._fusable("q_int", batch)  # each critic on its own path
    assert not make_loss(False)._fusable("q", batch)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # bf16 keeps the modules' rounding
        assert not loss._fusable("q", batch)
    images = TensorDict({"observation": torch.zeros(BATCH, 2, OBS_DIM // 2), "action": torch.zeros(BATCH, 2)},
                        [BATCH])
    assert not loss._fusable("q", images)
    wider = batch.clone().set("observation", torch.zeros(BATCH, OBS_DIM + 1))
    assert not loss._fusable("q", wider)  # a mismatched width goes to the module, which raises
    with pytest.raises(RuntimeError):
        loss(wider)
    loss(batch.clone())  # and the mixed loss runs


def test_the_recipe_field_reaches_the_loss(tmp_path):
    """The recipe's PERLHFLoss (``loss.objective=paper``; the default objective, proxy_value, has no fused path)
    takes the fused path. The field ``loss.fused_critics`` that picked it was retired (issue 43): refused on the
    command line, dropped from a run's saved config, whose loss is then fused as well."""
    from omegaconf import OmegaConf

    from pe_rlhf.algorithms.proxy_q import builders
    from pe_rlhf.algorithms.proxy_q.config import load_config
    from pe_rlhf.runtime.config_rules import ConfigError

    cfg = load_config(overrides=["profile=smoke", "loss.objective=paper"])
    loss, _ = builders.build_loss(cfg, builders.build_actor(cfg))
    assert isinstance(loss, PERLHFLoss) and loss.fused_critics is True and bool(loss._plans)
    with pytest.raises(ConfigError, match="unknown config key 'loss.fused_critics'"):
        load_config(overrides=["profile=smoke", "loss.objective=paper", "loss.fused_critics=false"])
    saved = OmegaConf.to_container(cfg)
    saved["loss"]["fused_critics"] = False  # a run folder's config.yaml from before issue 43
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(OmegaConf.create({"algorithm": "pe-rlhf", **saved})))
    old = load_config(path, apply_profile=False)
    assert "fused_critics" not in old.loss
    loss, _ = builders.build_loss(old, builders.build_actor(old))
    assert loss.fused_critics is True and bool(loss._plans)
