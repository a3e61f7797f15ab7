"""Issue 45, case 10: every baseline learner trains what it should: in a smoke run, every parameter of its actor
moves, and so does a parameter of every optimiser's group.

Before, rewiring SAC's actor optimiser onto the critic's parameters (an actor that never trains) passed every test
of ``test_baselines_rl.py``: they checked outputs and numbers, not that the actor learned.
"""

from __future__ import annotations

import pytest
import torch
from test_baselines_il import demos_dir  # noqa: F401 - the session fixture: 200 recorded demonstration steps

from pe_rlhf.algorithms.baselines import main
from pe_rlhf.runtime.run import Run

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore::FutureWarning"), pytest.mark.filterwarnings("ignore::UserWarning")]

RL = ("sac_rs", "sac_lag", "ppo_rs", "ppo_lag", "cpo")
IL = ("bc", "cql", "gail", "hg_dagger", "iwr")


def watched_run(method: str, argv: list[str], monkeypatch) -> dict:
    """Train ``method`` in this process, keeping the actor's and each optimiser's parameters from before the first
    update and the learner itself."""
    seen, real = {}, Run.train

    def train(self, out_dir, resume=False):
        objects = self.learner.checkpoint_objects()
        seen["learner"] = self.learner
        seen["actor"] = {k: v.detach().clone() for k, v in self.learner.actor.state_dict().items()}
        seen["optimizers"] = {name: [p.detach().clone() for g in opt.param_groups for p in g["params"]]
                              for name, opt in objects["optimizers"].items()}
        return real(self, out_dir, resume)

    monkeypatch.setattr(Run, "train", train)
    main(method, argv)
    return seen


def assert_trained(method: str, seen: dict) -> None:
    learner = seen["learner"]
    after = learner.actor.state_dict()
    still = [k for k, v in seen["actor"].items() if v.is_floating_point() and torch.equal(v, after[k])]
    assert not still, f"{method}: the actor's {still} never moved"
    optimizers = learner.checkpoint_objects()["optimizers"]
    for name, before in seen["optimizers"].items():
        now = [p.detach() for g in optimizers[name].param_groups for p in g["params"]]
        assert any(not torch.equal(b, n) for b, n in zip(before, now)), f"{method}: optimiser {name!r} moved nothing"


@pytest.mark.parametrize("method", RL)
def test_every_rl_baseline_trains_its_actor_and_every_optimiser(method, tmp_path, monkeypatch):
    assert_trained(method, watched_run(method, ["profile=smoke", "--out", str(tmp_path)], monkeypatch))


@pytest.mark.parametrize("method", IL)
def test_every_il_baseline_trains_its_actor_and_every_optimiser(method, tmp_path, monkeypatch, demos_dir):  # noqa: F811
    argv = ["profile=smoke", f"data.path={demos_dir}", "--out", str(tmp_path)]
    assert_trained(method, watched_run(method, argv, monkeypatch))
