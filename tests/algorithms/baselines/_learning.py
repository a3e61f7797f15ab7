"""Issue 45, case 10: a baseline's smoke run trains what it should. ``watched_main`` trains a method in this process
and keeps its actor's and each optimiser's parameters from before the first update and after the last, so that the
test module that already runs the smoke run checks them without a second run."""

from __future__ import annotations

import pytest
import torch

from pe_rlhf.algorithms.baselines import main
from pe_rlhf.runtime.run import Run


def _parameters(learner) -> tuple[dict, dict]:
    actor = {k: v.detach().clone() for k, v in learner.actor.state_dict().items()}
    optimizers = {name: [p.detach().clone() for g in opt.param_groups for p in g["params"]]
                  for name, opt in learner.checkpoint_objects()["optimizers"].items()}
    return actor, optimizers


def watched_main(method: str, argv: list[str]) -> dict:
    """``main(method, argv)``, returning the actor's and the optimisers' parameters before and after training."""
    seen, real = {}, Run.train

    def train(self, out_dir, resume=False):
        seen["before"] = _parameters(self.learner)
        result = real(self, out_dir, resume)
        seen["after"] = _parameters(self.learner)
        return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Run, "train", train)
        main(method, argv)
    return seen


def assert_trained(method: str, seen: dict) -> None:
    """Every floating actor parameter moved, and at least one parameter of every optimiser."""
    (actor_before, optimizers_before), (actor_after, optimizers_after) = seen["before"], seen["after"]
    still = [k for k, v in actor_before.items() if v.is_floating_point() and torch.equal(v, actor_after[k])]
    assert not still, f"{method}: the actor's {still} never moved"
    for name, before in optimizers_before.items():
        now = optimizers_after[name]
        assert any(not torch.equal(b, n) for b, n in zip(before, now)), f"{method}: optimiser {name!r} moved nothing"
