"""Tests of ``pe_rlhf.runtime.actor_selection.ActorSelection``: which snapshot it keeps, and its state."""

from __future__ import annotations

import pytest
import torch

from pe_rlhf.runtime.actor_selection import ActorSelection


def _summary(success: float, completion: float) -> dict:
    return {"success_rate": {"mean": success, "std": 0.0}, "route_completion": {"mean": completion, "std": 0.0}}


def _actor(value: float) -> torch.nn.Linear:
    layer = torch.nn.Linear(2, 1)
    torch.nn.init.constant_(layer.weight, value)
    return layer


def test_success_first_then_route_completion_then_the_later_snapshot():
    picking = ActorSelection(_actor(0.0), every=10, episodes=20)
    assert picking.consider(_actor(1.0), 10, _summary(0.5, 0.9)) is True
    assert picking.consider(_actor(2.0), 20, _summary(0.6, 0.1)) is True  # more successes win over completion
    assert picking.consider(_actor(3.0), 30, _summary(0.6, 0.05)) is False  # equal success, less completion
    assert picking.consider(_actor(4.0), 40, _summary(0.6, 0.1)) is True  # a tie: the later one
    assert picking.consider(_actor(5.0), 50, _summary(0.2, 1.0)) is False
    assert picking.step == 40 and torch.all(picking.actor.weight == 4.0)
    assert picking.row() == {"actor_selection/success_rate": 0.2, "actor_selection/route_completion": 1.0,
                             "actor_selection/picked_step": 40.0}
    assert not any(p.requires_grad for p in picking.actor.parameters())


def test_the_kept_copy_does_not_follow_the_live_actor():
    live = _actor(1.0)
    picking = ActorSelection(live, every=10, episodes=20)
    picking.consider(live, 10, _summary(1.0, 1.0))
    with torch.no_grad():
        live.weight.fill_(7.0)
    assert torch.all(picking.actor.weight == 1.0)


def test_state_round_trip_and_summary():
    picking = ActorSelection(_actor(0.0), every=10, episodes=20)
    picking.consider(_actor(1.0), 10, _summary(0.25, 0.5))
    picking.consider(_actor(1.0), 20, _summary(0.75, 0.5))
    again = ActorSelection(_actor(0.0), every=10, episodes=20)
    again.load_state_dict(picking.state_dict())
    assert again.scores == picking.scores and again.step == 20
    assert again.summary() == picking.summary()
    assert picking.summary()["scores"]["20"] == {"success_rate": 0.75, "route_completion": 0.5}


def test_test_scenes_are_refused():
    refused = r"ActorSelection\(split='test'\): the actor is picked on train scenes only.*allowed: 'train'"
    with pytest.raises(ValueError, match=refused):
        ActorSelection(_actor(0.0), every=10, episodes=20, split="test")


def test_more_scenes_than_the_split_has_are_refused():
    with pytest.raises(ValueError, match=r"actor_selection.episodes=51: allowed 1 to 50 \(the train scenes\)"):
        ActorSelection(_actor(0.0), every=10, episodes=51)
