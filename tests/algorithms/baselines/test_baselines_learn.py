"""Issue 45, case 10: the baseline learners improve their policy, not only move it: SAC-RS and SAC-Lag bring their
deterministic action near the optimum of a one-step bandit.

That every smoke run moves every actor parameter and a parameter of every optimiser is checked where the smoke
runs are trained, so that none is trained twice: ``test_every_rl_baseline_trains_its_actor_and_every_optimiser``
in ``test_baselines_rl.py`` and its IL twin in ``test_baselines_il.py``. Before, rewiring SAC's actor optimiser
onto the critic's parameters (an actor that never trains) passed every test that checked outputs and numbers.
"""

from __future__ import annotations

import pytest
import torch

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore::FutureWarning"), pytest.mark.filterwarnings("ignore::UserWarning")]


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
