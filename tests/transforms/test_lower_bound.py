"""The paper's Theorem 3 (lower bound) on a toy MDP, with an ensemble *trained* by fit_q_ensemble.

A point robot in the plane (state = position, action in [-1, 1]^2, step 0.1 * action) starts
near the origin and must reach the goal (2, 0); behind it (x < -0.5) is a pit. Reward per step:
20 * (progress towards the goal) - 10 on falling into the pit (terminal); reaching the goal
(distance < 0.1) is terminal; horizon 30. The physics policy is correct but mediocre (towards
the goal at half speed). The ensemble is fitted on warm-up data of the physics policy plus
noise (so it estimates Q of that policy, as in the paper), then the hybrid policy
``a = selector(s, a_mentor, a_phy)`` is rolled out with mentors of different quality.

Theorem 3: ``J(pi_hybrid) >= J(pi_phy)`` whatever the mentor; with a good mentor the hybrid
uses it and beats physics.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from pe_rlhf.modules.ensemble_training import add_next_actions
from pe_rlhf.objectives.q_ensemble_fit import fit_q_ensemble
from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.transforms.selector import HybridActionSelector

GOAL = torch.tensor([2.0, 0.0])
PIT_X, HORIZON, STEP, SCALE, PENALTY = -0.5, 30, 0.1, 20.0, 10.0
GAMMA = 0.9
EPISODES = 50


pytestmark = pytest.mark.usefixtures("one_thread_module")  # tiny nets: one thread


def reset(n, g):
    return torch.stack([torch.rand(n, generator=g) * 0.4 - 0.2, torch.rand(n, generator=g) - 0.5], -1)


def env_step(s, a):
    s2 = s + STEP * a.clamp(-1, 1)
    d, d2 = (GOAL - s).norm(dim=-1), (GOAL - s2).norm(dim=-1)
    pit = s2[:, 0] < PIT_X
    reward = SCALE * (d - d2) - PENALTY * pit.float()
    return s2, reward, pit | (d2 < 0.1)


def _towards_goal(s):
    v = GOAL - s
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-6)


def physics(s):  # correct but slow
    return 0.5 * _towards_goal(s)


def good_mentor(s):  # full speed to the goal
    return _towards_goal(s)


def bad_mentor(s):  # always wrong: full speed away from the goal, into the pit
    return -_towards_goal(s)


def fatigued_mentor(s):  # good at first, then turns back towards the pit
    return torch.where(s[:, :1] < 1.0, good_mentor(s), bad_mentor(s))


def rollout(policy, n=EPISODES, seed=123):
    """Undiscounted returns (n,) and, if ``policy`` returns (action, chosen), the mentor share."""
    g = torch.Generator().manual_seed(seed)
    s = reset(n, g)
    alive = torch.ones(n, dtype=torch.bool)
    ret = torch.zeros(n)
    chosen_steps = alive_steps = 0
    for _ in range(HORIZON):
        out = policy(s)
        a, chosen = out if isinstance(out, tuple) else (out, None)
        s2, r, term = env_step(s, a)
        ret += r * alive
        if chosen is not None:
            chosen_steps += (chosen[:, 0] & alive).sum().item()
        alive_steps += alive.sum().item()
        alive &= ~term
        s = torch.where(alive[:, None], s2, s)
        if not alive.any():
            break
    return ret, chosen_steps / alive_steps


def collect_warmup(n_episodes, sigma, seed):
    """Physics policy + N(0, sigma) noise; flat transitions with the next recorded action."""
    g = torch.Generator().manual_seed(seed)
    s = reset(n_episodes, g)
    alive = torch.ones(n_episodes, dtype=torch.bool)
    cols = {k: [] for k in ("obs", "act", "rew", "next_obs", "term", "trunc", "alive")}
    for t in range(HORIZON):
        a = (physics(s) + sigma * torch.randn(n_episodes, 2, generator=g)).clamp(-1, 1)
        s2, r, term = env_step(s, a)
        for k, v in zip(cols, (s, a, r, s2, term, torch.full_like(term, t == HORIZON - 1) & ~term, alive.clone())):
            cols[k].append(v)
        alive &= ~term
        s = s2
    c = {k: torch.stack(v, 1) for k, v in cols.items()}  # (N, T, ...)
    td = TensorDict({"observation": c["obs"], "action": c["act"],
                     "next": {"observation": c["next_obs"], "reward": c["rew"][..., None],
                              "terminated": c["term"][..., None], "truncated": c["trunc"][..., None],
                              "done": (c["term"] | c["trunc"])[..., None]}}, [n_episodes, HORIZON])
    add_next_actions(td)  # the warm-up policy's recorded action at s'
    return td[c["alive"]]  # drop the padding after each episode's end


@pytest.fixture(scope="module", params=["mean", "member"])
def selector(request):
    data = collect_warmup(200, sigma=0.6, seed=0)
    torch.manual_seed(0)
    q = QEnsemble(2, 2, num_members=5, hidden=(64, 64))
    info = fit_q_ensemble(q, data, steps=400, gamma=GAMMA, lr=1e-3, loss=request.param, seed=0)
    q.requires_grad_(False)
    print(f"\n[{request.param}] warm-up transitions {data.shape[0]}, TD loss "
          f"{info['first_loss']:.3f} -> {info['final_loss']:.3f}")
    return HybridActionSelector(q, epsilon_select=0.5)


def _hybrid(selector, mentor):
    return lambda s: selector.select(s, mentor(s), physics(s))


def test_toy_mdp_is_meaningful():
    j_phy = rollout(physics)[0].mean().item()
    assert rollout(bad_mentor)[0].mean().item() < j_phy - 30  # the bad mentor falls into the pit
    assert rollout(good_mentor)[0].mean().item() > j_phy + 5
    assert rollout(fatigued_mentor)[0].mean().item() < j_phy - 5  # it dithers at x = 1


def test_lower_bound_with_adversarial_mentor(selector):
    j_phy = rollout(physics)[0].mean().item()
    j_mentor = rollout(bad_mentor)[0].mean().item()
    ret, mentor_share = rollout(_hybrid(selector, bad_mentor))
    print(f"bad mentor: J_phy {j_phy:.2f} J_mentor {j_mentor:.2f} J_hybrid {ret.mean():.2f} "
          f"mentor share {mentor_share:.3f}")
    assert ret.mean().item() >= j_phy - 0.5
    assert mentor_share < 0.1


def test_good_mentor_is_used_and_beats_physics(selector):
    j_phy = rollout(physics)[0].mean().item()
    j_mentor = rollout(good_mentor)[0].mean().item()
    ret, mentor_share = rollout(_hybrid(selector, good_mentor))
    print(f"good mentor: J_phy {j_phy:.2f} J_mentor {j_mentor:.2f} J_hybrid {ret.mean():.2f} "
          f"mentor share {mentor_share:.3f}")
    assert mentor_share > 0.5
    assert ret.mean().item() > j_phy + 5


def test_fatigued_mentor_helps_then_is_overruled(selector):
    j_phy = rollout(physics)[0].mean().item()
    ret, mentor_share = rollout(_hybrid(selector, fatigued_mentor))
    print(f"fatigued mentor: J_phy {j_phy:.2f} J_hybrid {ret.mean():.2f} mentor share {mentor_share:.3f}")
    assert ret.mean().item() > j_phy + 2  # it used the good phase ...
    assert 0.2 < mentor_share < 0.8  # ... and rejected the bad one
