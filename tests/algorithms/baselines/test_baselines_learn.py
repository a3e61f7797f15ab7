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


@pytest.mark.parametrize("lagrangian", [False, True])
def test_sac_improves_its_policy_on_a_one_step_bandit(lagrangian):
    """Reward ``-|a - (0.5, -0.3)|^2`` at every state, episodes of one step, no cost: after 15 batches of 20 updates
    the deterministic action is near the optimum (from 0.61 away to 0.07 measured), for SAC-RS and SAC-Lag."""
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from pe_rlhf.algorithms.baselines import EpisodeTracker, load_baseline_config
    from pe_rlhf.algorithms.baselines.algorithms import SACLearner

    torch.manual_seed(0)
    method = "sac_lag" if lagrangian else "sac_rs"
    cfg = load_baseline_config(method, overrides=["profile=smoke", "optim.lr=0.003", "collector.learning_starts=0",
                                                  "optim.updates_per_batch=20", "replay_buffer.batch_size=64"])
    obs_dim, best = 3, torch.tensor([0.5, -0.3])
    learner, tracker = SACLearner(cfg, obs_dim, lagrangian=lagrangian), EpisodeTracker()
    g = torch.Generator().manual_seed(1)
    probe = TensorDict({"observation": torch.randn(64, obs_dim, generator=g)}, [64])

    def distance() -> float:
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            return float((learner.actor(probe.clone())["action"] - best).norm(dim=-1).mean())

    before = distance()
    for i in range(15):
        obs, action = torch.randn(64, obs_dim, generator=g), torch.rand(64, 2, generator=g) * 2 - 1
        one = torch.ones(64, 1, dtype=torch.bool)
        batch = TensorDict({"observation": obs, "action": action,
                            "next": {"observation": obs.clone(), "reward": -((action - best) ** 2).sum(-1, keepdim=True),
                                     "cost": torch.zeros(64, 1), "done": one, "terminated": one, "success": ~one,
                                     "sim_error": ~one}}, [64])
        learner.learn(batch, 64 * (i + 1), tracker)
    after = distance()
    assert before > 0.4 and after < 0.25 and after < before / 2, (before, after)
