"""Tests of ``ProxyValueLoss`` (PVP's bounded proxy values): closed-form terms with hand-built critics whose copies
hold different values, renamed keys, the policy delay, a degenerate batch, and a chain on which the propagated
values order the states."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives.utils import ValueEstimators

from pe_rlhf.modules import make_deterministic_actor, make_qvalue
from pe_rlhf.objectives import ForeachSoftUpdate, ProxyValueLoss, make_adam
from pe_rlhf.objectives.perlhf import make_transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")

OBS, ACT = 3, 2


class LinearQ(nn.Module):
    """``Q(s, a) = w_s . s + w_a . a + b``: every value and target is known in closed form."""

    def __init__(self):
        super().__init__()
        self.w_s, self.w_a, self.b = nn.Parameter(torch.zeros(OBS)), nn.Parameter(torch.zeros(ACT)), nn.Parameter(
            torch.zeros(()))

    def forward(self, observation, action):
        return (observation @ self.w_s + action @ self.w_a + self.b).unsqueeze(-1)


class ConstantAction(nn.Module):
    """``pi(s) = c``, whatever the state."""

    def __init__(self, action):
        super().__init__()
        self.c = nn.Parameter(torch.as_tensor(action, dtype=torch.float32))

    def forward(self, observation):
        return self.c.expand(*observation.shape[:-1], ACT)


def hand_built_loss(**kwargs) -> ProxyValueLoss:
    """Twin linear critics with different known parameters (so the min over copies matters); their targets differ
    from them too; the actor proposes (0.2, -0.4) now and its target (0.6, 0.1)."""
    kwargs.setdefault("target_noise", 0.0)
    actor = TensorDictModule(ConstantAction([0.2, -0.4]), in_keys=["observation"], out_keys=["action"])
    qvalue = TensorDictModule(LinearQ(), in_keys=["observation", "action"], out_keys=["state_action_value"])
    loss = ProxyValueLoss(actor, qvalue, **kwargs)
    with torch.no_grad():
        q, q_target = loss.qvalue_network_params["module"], loss.target_qvalue_network_params["module"]
        q["w_s"].copy_(torch.tensor([[1.0, 0.0, -1.0], [0.5, 0.5, 0.0]]))
        q["w_a"].copy_(torch.tensor([[1.0, 2.0], [-1.0, 0.5]]))
        q["b"].copy_(torch.tensor([0.1, -0.2]))
        q_target["w_s"].copy_(torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0]]))
        q_target["w_a"].copy_(torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
        q_target["b"].copy_(torch.tensor([0.3, -0.1]))
        loss.target_actor_network_params["module", "c"].copy_(torch.tensor([0.6, 0.1]))
    return loss


def batch(seed: int = 0, rows: int = 6, takeover=(1, 1, 0, 0, 0, 1), start=(1, 0, 0, 0, 0, 1),
          terminated=(0, 0, 0, 1, 0, 0)) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    obs, nxt = torch.randn(rows, OBS, generator=g), torch.randn(rows, OBS, generator=g)
    agent = torch.rand(rows, ACT, generator=g) * 2 - 1
    executed = agent.clone()
    flags = torch.tensor(takeover, dtype=torch.bool).unsqueeze(-1)
    executed[flags.squeeze(-1)] = torch.rand(int(flags.sum()), ACT, generator=g) * 2 - 1
    return make_transitions(obs, nxt, agent, executed, flags, torch.tensor(start, dtype=torch.bool).unsqueeze(-1),
                            torch.tensor(terminated, dtype=torch.bool).unsqueeze(-1))


def q_by_hand(params, obs, action):
    """``(copies, rows)`` values of the linear critics under ``params``."""
    p = params["module"]
    return (obs @ p["w_s"].T + action @ p["w_a"].T + p["b"]).T


def td_errors_by_hand(td) -> torch.Tensor:
    """``(copies, rows)``: the hand-built critics' TD errors at the executed action (``gamma`` 0.99, no target
    noise, the target actor's constant (0.6, 0.1))."""
    loss = hand_built_loss()
    with torch.no_grad():
        q = q_by_hand(loss.qvalue_network_params, td["observation"], td["next", "behavior_action"])
        next_q = q_by_hand(loss.target_qvalue_network_params, td["next", "observation"],
                           torch.tensor([0.6, 0.1]).expand(len(td), 2)).min(0)[0]
        return q - 0.99 * (1 - td["next", "terminated"].squeeze(-1).float()) * next_q


# --------------------------------------------------------------------------- closed-form terms


def test_terms_match_their_closed_form_with_twin_critics_of_different_values():
    loss = hand_built_loss(q_value_bound=2.0, gamma=0.9, policy_delay=1, bc_weight=0.5)
    td = batch()
    out = loss(td)
    obs, nxt = td["observation"], td["next", "observation"]
    agent, executed = td["action"], td["next", "behavior_action"]
    takeover = td["next", "intervention"].squeeze(-1)
    terminated = td["next", "terminated"].squeeze(-1).float()
    with torch.no_grad():
        q = q_by_hand(loss.qvalue_network_params, obs, executed)  # (2, 6)
        next_q = q_by_hand(loss.target_qvalue_network_params, nxt, torch.tensor([0.6, 0.1]).expand(6, 2))
        assert not torch.allclose(next_q[0], next_q[1])  # the min over the copies picks per row
        target = 0.9 * (1 - terminated) * next_q.min(0)[0]
        td_loss = (q - target).pow(2).mean(-1).sum()
        q_agent = q_by_hand(loss.qvalue_network_params, obs[takeover], agent[takeover])
        proxy = ((q[:, takeover] - 2.0).pow(2).mean(-1) + (q_agent + 2.0).pow(2).mean(-1)).sum()
        policy = torch.tensor([0.2, -0.4]).expand(6, 2)
        q_policy = q_by_hand(loss.qvalue_network_params, obs, policy)[0]  # the first critic only
        bc = (policy[takeover] - executed[takeover]).pow(2).sum(-1).mean()
    torch.testing.assert_close(out["td_loss"], td_loss)
    torch.testing.assert_close(out["proxy_loss"], proxy)
    torch.testing.assert_close(out["loss_qvalue"], td_loss + proxy, check_dtype=False)
    torch.testing.assert_close(out["bc_loss"], bc)
    torch.testing.assert_close(out["loss_actor"], -q_policy.mean() + 0.5 * bc)
    torch.testing.assert_close(out["q_behavior"], q.mean(0)[takeover].mean())
    torch.testing.assert_close(out["q_agent"], q_agent.mean())
    torch.testing.assert_close(out["q_free"], q.mean(0)[~takeover].mean())
    assert out["intervention_rate"].item() == pytest.approx(0.5)


def test_the_mask_leaves_takeover_start_rows_out_of_the_td_term():
    td = batch()
    start = td["next", "intervention_start"].squeeze(-1)
    masked, plain = hand_built_loss(mask_td_at_takeover_start=True)(td), hand_built_loss()(td)
    expected = td_errors_by_hand(td)[:, ~start].pow(2).mean(-1).sum()
    torch.testing.assert_close(masked["td_loss"], expected)
    assert masked["td_loss"] != plain["td_loss"]
    torch.testing.assert_close(masked["proxy_loss"], plain["proxy_loss"])


def test_the_batch_reduction_is_pvps_released_loss():
    """``proxy_reduction="batch"``: both labels' squared errors averaged over the whole batch (agent rows, where the
    proposal is the executed action, pulled to +B and -B at once), times the takeover share; TD weighted 0.5."""
    td = batch()
    takeover = td["next", "intervention"].squeeze(-1)
    loss = hand_built_loss(q_value_bound=2.0, proxy_reduction="batch")
    out = loss(td)
    with torch.no_grad():
        obs, executed, agent = td["observation"], td["next", "behavior_action"], td["action"]
        q = q_by_hand(loss.qvalue_network_params, obs, executed)
        q_agent = q_by_hand(loss.qvalue_network_params, obs, agent)
        next_q = q_by_hand(loss.target_qvalue_network_params, td["next", "observation"],
                           torch.tensor([0.6, 0.1]).expand(6, 2)).min(0)[0]
        target = 0.99 * (1 - td["next", "terminated"].squeeze(-1).float()) * next_q
        td_loss = 0.5 * (q - target).pow(2).mean(-1).sum()
        proxy = takeover.float().mean() * ((q - 2.0).pow(2).mean(-1) + (q_agent + 2.0).pow(2).mean(-1)).sum()
    torch.testing.assert_close(out["td_loss"], td_loss)
    torch.testing.assert_close(out["proxy_loss"], proxy)
    torch.testing.assert_close(out["q_agent"], q_agent.mean(0)[takeover].mean())
    without = batch(takeover=(0,) * 6, start=(0,) * 6)
    assert hand_built_loss(proxy_reduction="batch")(without)["proxy_loss"].item() == 0.0
    with pytest.raises(ValueError, match="proxy_reduction='rows' is invalid"):
        hand_built_loss(proxy_reduction="rows")


def test_target_noise_is_clipped_and_the_target_action_stays_in_bounds():
    loss = hand_built_loss(target_noise=10.0, target_noise_clip=0.3)
    td = batch()
    torch.manual_seed(0)
    target = loss.td_target(td)
    # every noisy target action lies within 0.3 of (0.6, 0.1): the target is bracketed by the critics' extremes
    corners = torch.tensor([[0.3, -0.2], [0.3, 0.4], [0.9, -0.2], [0.9, 0.4]])
    nxt = td["next", "observation"]
    values = torch.stack([q_by_hand(loss.target_qvalue_network_params, nxt, c.expand(6, 2)) for c in corners])
    not_terminal = 1 - td["next", "terminated"].squeeze(-1).float()
    low = 0.99 * not_terminal * values.min(1)[0].min(0)[0]
    high = 0.99 * not_terminal * values.max(1)[0].max(0)[0]
    assert torch.all(target >= low - 1e-6) and torch.all(target <= high + 1e-6)


# --------------------------------------------------------------------------- the TorchRL contract, keys, delay


def test_renamed_keys_give_the_same_numbers():
    td = batch()
    renamed = TensorDict({"observation": td["observation"], "proposal": td["action"],
                          "next": {"observation": td["next", "observation"], "done": td["next", "done"],
                                   "end": td["next", "terminated"], "executed": td["next", "behavior_action"],
                                   "took_over": td["next", "intervention"],
                                   "took_over_now": td["next", "intervention_start"]}}, [6])
    loss = hand_built_loss(policy_delay=1)
    loss.set_keys(action="proposal", behavior_action=("next", "executed"), intervention=("next", "took_over"),
                  intervention_start=("next", "took_over_now"), terminated="end")
    reference = hand_built_loss(policy_delay=1)(td)
    out = loss(renamed)
    for key in ("loss_qvalue", "td_loss", "proxy_loss", "q_agent"):
        torch.testing.assert_close(out[key], reference[key])
    assert "proposal" in loss.in_keys and ("next", "took_over") in loss.in_keys
    # the policy's own action key stays "action" (the actor writes it), so only the stored proposal is renamed


def test_torchrl_contract_repr_out_keys_and_value_estimator():
    loss = ProxyValueLoss(make_deterministic_actor(OBS), make_qvalue(OBS))
    text = repr(loss)
    assert "ProxyValueLoss" in text and "in_keys" in text
    assert set(loss.out_keys) <= set(loss(batch()).keys())
    assert loss.make_value_estimator(ValueEstimators.TD0, gamma=0.95) is loss and loss.gamma == 0.95
    with pytest.raises(NotImplementedError, match="allowed: \\['TD0'\\]"):
        loss.make_value_estimator(ValueEstimators.GAE)


def test_the_actor_term_runs_every_policy_delay_calls_and_the_count_is_saved():
    loss = hand_built_loss(policy_delay=3)
    actor_terms = [float(loss(batch())["loss_actor"]) for _ in range(6)]
    assert [t != 0.0 for t in actor_terms] == [False, False, True, False, False, True]
    state = loss.state_dict()
    fresh = hand_built_loss(policy_delay=3)
    fresh.load_state_dict(state)
    assert int(fresh.calls) == 6 and float(fresh(batch())["loss_actor"]) == 0.0


def test_a_batch_without_takeover_rows_stays_finite():
    loss = ProxyValueLoss(make_deterministic_actor(OBS), make_qvalue(OBS, layer_norm=True), policy_delay=1,
                          bc_weight=1.0)
    out = loss(batch(takeover=(0,) * 6, start=(0,) * 6))
    assert all(torch.isfinite(v).all() for v in out.values())
    assert out["proxy_loss"] == 0 and out["q_agent"] == 0 and out["bc_loss"] == 0 and out["intervention_rate"] == 0
    (out["loss_qvalue"] + out["loss_actor"]).backward()


@pytest.mark.parametrize("field,value", [("q_value_bound", 0.0), ("gamma", 1.5), ("policy_delay", 0),
                                         ("target_noise", -0.1), ("bc_weight", float("nan"))])
def test_bad_arguments_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        ProxyValueLoss(make_deterministic_actor(OBS), make_qvalue(OBS), **{field: value})


# --------------------------------------------------------------------------- propagation on a chain


def test_values_propagate_down_a_chain_in_order():
    """s0 -> s1 -> s2 -> s3 under the agent's action +0.5; at s3 the mentor takes over (the proposal +0.5 is
    labelled -1, the executed -0.5 +1) and the episode ends. Zero-reward TD carries the -1 back: the further a
    state is from the takeover, the higher the agent's action is valued there, ~ -gamma^k."""
    torch.manual_seed(0)
    states = torch.eye(4)
    gamma = 0.8
    actor = TensorDictModule(ConstantAction([0.5, 0.0]), in_keys=["observation"], out_keys=["action"])
    loss = ProxyValueLoss(actor, make_qvalue(4, hidden=(32, 32)), gamma=gamma, target_noise=0.0, policy_delay=10**6)
    soft = ForeachSoftUpdate(loss, tau=0.05)
    agent = torch.tensor([[0.5, 0.0]]).expand(4, 2)
    executed = agent.clone()
    executed[3] = torch.tensor([-0.5, 0.0])
    takeover = torch.tensor([[0], [0], [0], [1]], dtype=torch.bool)
    td = make_transitions(states, torch.cat([states[1:], states[3:]]), agent, executed, takeover, takeover,
                          takeover.clone())
    optimizer = make_adam(loss.qvalue_network_params.flatten_keys().values(), lr=3e-3)
    for _ in range(1500):
        out = loss(td)
        optimizer.zero_grad()
        out["loss_qvalue"].backward()
        optimizer.step()
        soft.step()
    with torch.no_grad():
        q = loss._q(loss.qvalue_network_params, td, agent).mean(0)
        q_exec = loss._q(loss.qvalue_network_params, td, executed).mean(0)
    assert q[0] > q[1] > q[2] > q[3]
    torch.testing.assert_close(q, torch.tensor([-gamma ** 3, -gamma ** 2, -gamma, -1.0]), atol=0.08, rtol=0)
    # its +1 label (weight 1: the mean over the one takeover row) and its terminal TD target 0 (weight 1/4: the mean
    # over the four rows) share the row: (1 * 1 + 0.25 * 0) / 1.25
    assert q_exec[3] == pytest.approx(0.8, abs=0.05)
