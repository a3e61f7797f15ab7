"""Issue 45, case 10: every TD target of ``PERLHFLoss`` takes the *minimum* over its target critics, shown with target
copies that hold different values (derived by hand, not recorded from the code's output): taking ``max`` (or one
copy) instead fails here. The same for the actor's online minimum over each critic it reads.

Before, every TD-target test gave both target copies the same value, so such a bug was caught only by numbers the
code had produced itself (``PREVIOUS_OUTPUTS``).
"""

from __future__ import annotations

import pytest
import torch
from test_perlhf_loss import (BATCH, ConstantQ, critic, disturbance_loss, make_batch, make_loss, run, set_online,
                              with_disturbance)

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")


def set_target(params, values) -> None:
    """The target copies of a hand-built ``ConstantQ`` critic: one value per copy."""
    params.get(("module", "value")).data.copy_(torch.as_tensor(values, dtype=torch.float32))


def test_reward_critic_target_is_the_min_over_distinct_target_copies():
    terminated = (torch.arange(BATCH) % 2 == 0).unsqueeze(-1)
    batch = make_batch(terminated=terminated)
    gamma = 0.9
    loss = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(0.0)), gamma=gamma, alpha_init=1e-9, fixed_alpha=True)
    set_online(loss.qvalue_network_params, "value", [1.0, 3.0])
    set_target(loss.target_qvalue_network_params, [5.0, 2.0])  # min 2, max 5, first 5
    out = run(loss, batch)
    y = gamma * 2.0 * (~terminated.squeeze(-1)).float()
    expected = 0.5 * sum(((c - y) ** 2).mean() for c in (1.0, 3.0))
    assert out["td_loss"] == pytest.approx(expected.item(), rel=1e-5)


def test_intervention_critic_target_is_the_min_over_distinct_target_copies():
    start = (torch.arange(BATCH) % 3 == 0).unsqueeze(-1)
    terminated = (torch.arange(BATCH) % 2 == 0).unsqueeze(-1)
    batch = make_batch(intervention=1.0, start=start, terminated=terminated)
    gamma = 0.8
    loss = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(0.0)), gamma=gamma)
    set_online(loss.intervention_qvalue_network_params, "value", [1.0, 3.0])
    set_target(loss.target_intervention_qvalue_network_params, [4.0, 1.5])  # min 1.5
    out = run(loss, batch)
    target = (batch["next", "intervention_cost"].squeeze(-1) * start.squeeze(-1)
              + gamma * 1.5 * (~terminated.squeeze(-1)).float())
    expected = 0.5 * sum(((d - target) ** 2).mean() for d in (1.0, 3.0))
    assert out["loss_intervention_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)


def test_disturbance_critic_target_is_the_min_over_distinct_target_copies():
    terminated = (torch.arange(BATCH) % 2 == 0).unsqueeze(-1)
    cost = torch.rand(BATCH, 1, generator=torch.Generator().manual_seed(7))
    batch = with_disturbance(make_batch(intervention=0.5, terminated=terminated), cost)
    gamma = 0.8
    loss = disturbance_loss(critic(ConstantQ(0.0)), gamma=gamma)
    set_online(loss.disturbance_qvalue_network_params, "value", [1.0, 3.0])
    set_target(loss.target_disturbance_qvalue_network_params, [6.0, 0.5])  # min 0.5
    out = run(loss, batch)
    target = cost.squeeze(-1) + gamma * 0.5 * (~terminated.squeeze(-1)).float()
    expected = 0.5 * sum(((d - target) ** 2).mean() for d in (1.0, 3.0))
    assert out["loss_disturbance_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)


def test_the_actor_reads_the_min_of_distinct_online_copies_of_both_critics():
    batch = make_batch(intervention=0.5)
    alpha, psi, beta = 0.5, 1.0, 1.0
    loss = make_loss(critic(ConstantQ(0.0)), critic(ConstantQ(0.0)), alpha_init=alpha, fixed_alpha=True,
                     psi=psi, intervention_weight=beta)
    set_online(loss.qvalue_network_params, "value", [4.0, 2.5])  # min 2.5
    set_online(loss.intervention_qvalue_network_params, "value", [0.75, 0.25])  # min 0.25
    out = run(loss, batch)
    expected = -alpha * out["entropy"].item() - psi * 2.5 + beta * 0.25
    assert out["loss_actor"].item() == pytest.approx(expected, rel=1e-5)
