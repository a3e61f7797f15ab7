"""Issue 45, case 10: every baseline learner's policy improves on a toy problem whose optimum is known.

A one-step bandit: random states, episodes of one step, the best action ``(0.5, -0.3)`` at every state. PPO-RS,
PPO-Lag and CPO learn from the reward ``-|a - best|^2`` (no cost); GAIL from demonstrations of ``best``; HG-DAgger and
IWR from a mentor who takes over, executing ``best``, whenever the agent's action is more than 0.15 from it. Each
learner's ``learn`` gets the batches its loop would hand it, and its deterministic action on 64 probe states must end
far nearer the optimum than it started (measured: from 0.61 away to 0.02-0.09). The parameters-move tests of the
same learners are in ``test_baselines_learn.py``; SAC-RS and SAC-Lag's bandit is there, BC's fit to labels in
``test_baselines_il.py``.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from pe_rlhf.algorithms.baselines import EpisodeTracker, load_baseline_config
from pe_rlhf.transforms.keys import BEHAVIOR_ACTION, INTERVENTION, INTERVENTION_START

pytestmark = [pytest.mark.usefixtures("one_thread_module"), pytest.mark.filterwarnings("ignore::UserWarning")]

OBS_DIM, BEST, N = 3, torch.tensor([0.5, -0.3]), 128


def distance(actor, probe: TensorDict) -> float:
    """Mean distance of the deterministic action from the optimum over ``probe``'s states."""
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        return float((actor(probe.clone())["action"] - BEST).norm(dim=-1).mean())


def bandit_steps(actor, g: torch.Generator, exploration=ExplorationType.RANDOM) -> TensorDict:
    """``N`` one-step episodes of ``actor`` (its sampled action, log-prob, ``loc``, ``scale``), with their reward."""
    obs = torch.randn(N, OBS_DIM, generator=g)
    with set_exploration_type(exploration), torch.no_grad():
        steps = actor(TensorDict({"observation": obs}, [N]))
    one = torch.ones(N, 1, dtype=torch.bool)
    steps["next"] = TensorDict({"observation": obs.clone(), "reward": -((steps["action"] - BEST) ** 2).sum(-1, True),
                                "cost": torch.zeros(N, 1), "done": one, "terminated": one, "success": ~one,
                                "sim_error": ~one}, [N])
    return steps


def improve(learner, batches: int, steps) -> tuple[float, float]:
    """``batches`` calls of ``learner.learn`` on ``steps(g)``; the distance to the optimum before and after."""
    g = torch.Generator().manual_seed(1)
    probe = TensorDict({"observation": torch.randn(64, OBS_DIM, generator=g)}, [64])
    before, tracker = distance(learner.actor, probe), EpisodeTracker()
    for i in range(batches):
        learner.learn(steps(g), N * (i + 1), tracker)
    return before, distance(learner.actor, probe)


def config(method: str, *overrides: str):
    return load_baseline_config(method, overrides=["profile=smoke", f"collector.frames_per_batch={N}", *overrides])


@pytest.mark.parametrize("method", ["ppo_rs", "ppo_lag", "cpo"])
def test_on_policy_learners_improve_their_policy_on_a_one_step_bandit(method):
    from pe_rlhf.algorithms.baselines.algorithms import CPOLearner, PPOLearner

    torch.manual_seed(0)
    if method == "cpo":
        learner = CPOLearner(config(method, "optim.lr=0.003", "loss.target_kl=0.05", "optim.minibatch_size=64",
                                    "optim.epochs=4"), OBS_DIM)
    else:
        learner = PPOLearner(config(method, "optim.lr=0.003", "optim.minibatch_size=64", "optim.epochs=4",
                                    "loss.normalize_advantage=true"), OBS_DIM, lagrangian=method == "ppo_lag")
    before, after = improve(learner, 30, lambda g: bandit_steps(learner.actor, g))
    assert before > 0.5 and after < 0.25 and after < before / 2, (method, before, after)


def test_gail_improves_its_policy_toward_the_demonstrated_action(monkeypatch):
    from pe_rlhf.algorithms.baselines import imitation_learners

    def demonstrations(cfg, run_dir):  # the mentor's steps: the optimum, a little noise
        g = torch.Generator().manual_seed(2)
        obs, action = torch.randn(512, OBS_DIM, generator=g), BEST + 0.05 * torch.randn(512, 2, generator=g)
        zero = torch.zeros(512, 1)
        return TensorDict({"observation": obs, "action": action,
                           "next": {"done": zero.bool(), "cost": zero}}, [512])

    monkeypatch.setattr(imitation_learners, "demonstrations", demonstrations)
    torch.manual_seed(0)
    learner = imitation_learners.GAILLearner(config("gail", "optim.lr=0.003", "optim.minibatch_size=64",
                                                    "optim.epochs=4", "loss.normalize_advantage=true"), OBS_DIM, None)
    before, after = improve(learner, 30, lambda g: bandit_steps(learner.actor, g))
    assert before > 0.5 and after < 0.25 and after < before / 2, (before, after)


@pytest.mark.parametrize("weighted", [False, True], ids=["hg_dagger", "iwr"])
def test_human_in_the_loop_imitation_improves_its_policy_under_a_correcting_mentor(weighted):
    from pe_rlhf.algorithms.baselines.imitation_learners import InterventionLearner

    torch.manual_seed(0)
    method = "iwr" if weighted else "hg_dagger"
    learner = InterventionLearner(config(method, "optim.lr=0.003"), OBS_DIM, None, weighted=weighted)

    def corrected(g: torch.Generator) -> TensorDict:
        steps = bandit_steps(learner.actor, g, ExplorationType.DETERMINISTIC)
        takeover = (steps["action"] - BEST).norm(dim=-1, keepdim=True) > 0.15
        steps["next", INTERVENTION], steps["next", INTERVENTION_START] = takeover, takeover
        steps["next", BEHAVIOR_ACTION] = torch.where(takeover, BEST.expand(N, 2), steps["action"])
        return steps

    before, after = improve(learner, 10, corrected)
    assert before > 0.5 and after < 0.2 and after < before / 3, (method, before, after)
