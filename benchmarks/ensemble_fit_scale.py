"""Is the Q-ensemble fitted on warm-up data at the scale of the returns, and how often does it prefer the mentor?

    python benchmarks/ensemble_fit_scale.py [--steps 10000] [--fits 3000:0.005 3000:0.05] [--lanes]
        [--physics-stop] [--epsilon 0.5] [--seed 0] [--json out.json]

The professional drives ``--steps`` train steps alone (PE-RLHF's warm-up); at every state IDM-MOBIL's action
(the physics proposal, obstacle-blind or ``--physics-stop``) is recorded beside the mentor's. For each
``FIT_STEPS:TAU`` a fresh 5-member ensemble (256x256, the recipe's selector defaults: Adam 3e-4, batch 256,
target noise 0.1, the paper's mean loss) is fitted with :func:`pe_rlhf.objectives.fit_q_ensemble` and
compared with the data's discounted Monte-Carlo returns (gamma 0.99, cut at the end of the data):
mean Q vs mean return, their correlation, and the advantage ``mean_k Q_k(s, a_mentor) - Q_k(s, a_phy)``
on the recorded states: its percentiles, the share of states where it reaches ``--epsilon`` (the
selector would execute the mentor there) and the same share on the states where the two actions
differ most (top 10% by action distance: lane changes, braking for obstacles).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch
from tensordict import TensorDict

from pe_rlhf.envs import DrivingConfig, make_gym_env, scene_seeds
from pe_rlhf.mentors import make_mentor
from pe_rlhf.modules import QEnsemble, add_next_actions
from pe_rlhf.objectives import fit_q_ensemble
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.physics.policy import PhysicsConfig

GAMMA = 0.99


def collect(steps: int, lanes: bool, physics_stop: bool, seed: int) -> TensorDict:
    rng = np.random.default_rng(seed)
    env = make_gym_env(DrivingConfig(split="train", lane_features=lanes))
    mentor, phys = make_mentor("professional", seed), IDMMobilPolicy(PhysicsConfig(stop_for_obstacles=physics_stop))
    cols = {k: [] for k in ("obs", "act", "phy", "rew", "next", "term", "done")}
    n = 0
    while n < steps:
        obs, _ = env.reset(options={"scene_seed": int(rng.choice(scene_seeds("train")))})
        mentor.reset(env)
        phys.reset()
        done = False
        while not done and n < steps:
            a_phy = np.asarray(phys(env), dtype=np.float32)
            a = np.asarray(mentor.act(env), dtype=np.float32)
            nobs, r, term, trunc, _ = env.step(a)
            n += 1
            done = term or trunc
            for k, v in zip(cols, (obs, a, a_phy, r, nobs, term, done or n == steps)):
                cols[k].append(v)
            obs = nobs
    t = {k: torch.as_tensor(np.array(v)) for k, v in cols.items()}
    td = TensorDict({"observation": t["obs"].float(), "action": t["act"], "physics_action": t["phy"],
                     "next": {"observation": t["next"].float(), "reward": t["rew"].float()[:, None],
                              "terminated": t["term"][:, None], "done": t["done"][:, None]}}, [n])
    returns = torch.zeros(n)
    acc = 0.0
    for i in reversed(range(n)):
        acc = float(t["rew"][i]) + (0.0 if bool(t["done"][i]) else GAMMA * acc)
        returns[i] = acc
    td.set("mc_return", returns)
    return add_next_actions(td)


def evaluate_fit(td: TensorDict, fit_steps: int, tau: float, epsilon: float, seed: int) -> dict:
    ens = QEnsemble(td["observation"].shape[-1], num_members=5, hidden=(256, 256))
    torch.manual_seed(seed)
    started = time.time()
    info = fit_q_ensemble(ens, td, steps=fit_steps, batch_size=256, gamma=GAMMA, tau=tau, seed=seed)
    seconds = time.time() - started
    with torch.no_grad():
        q_m = ens.values(td["observation"], td["action"]).mean(0)
        q_p = ens.values(td["observation"], td["physics_action"]).mean(0)
    adv = (q_m - q_p).numpy()
    ret = td["mc_return"].numpy()
    dist = (td["action"] - td["physics_action"]).norm(dim=-1).numpy()
    top = dist >= np.percentile(dist, 90)
    return {
        "fit_steps": fit_steps, "tau": tau, "fit_seconds": seconds, "final_loss": info["final_loss"],
        "q_mean": float(q_m.mean()), "mc_return_mean": float(ret.mean()),
        "q_return_corr": float(np.corrcoef(q_m.numpy(), ret)[0, 1]),
        "advantage_pcts_5_50_95": np.percentile(adv, [5, 50, 95]).round(3).tolist(),
        "mentor_chosen_share": float(np.mean(adv >= epsilon)),
        "mentor_chosen_share_top10_disagreement": float(np.mean(adv[top] >= epsilon)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10000)
    parser.add_argument("--fits", nargs="+", default=["3000:0.005", "3000:0.05"], metavar="STEPS:TAU")
    parser.add_argument("--lanes", action="store_true", help="env.lane_features=true")
    parser.add_argument("--physics-stop", action="store_true", help="physics.obstacles=stop (IDM brakes for obstacles)")
    parser.add_argument("--epsilon", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    started = time.time()
    td = collect(args.steps, args.lanes, args.physics_stop, args.seed)
    print(f"collected {td.shape[0]} steps in {time.time() - started:.0f}s; mean MC return "
          f"{td['mc_return'].mean():.1f}", flush=True)
    results = []
    for spec in args.fits:
        steps, tau = spec.split(":")
        r = evaluate_fit(td, int(steps), float(tau), args.epsilon, args.seed)
        results.append(r)
        print(f"fit {r['fit_steps']} steps, tau {r['tau']}: Q mean {r['q_mean']:.1f} vs MC return "
              f"{r['mc_return_mean']:.1f} (corr {r['q_return_corr']:.2f}); advantage p5/50/95 "
              f"{r['advantage_pcts_5_50_95']}; mentor chosen {r['mentor_chosen_share']:.2f} of states, "
              f"{r['mentor_chosen_share_top10_disagreement']:.2f} where they differ most "
              f"({r['fit_seconds']:.0f}s)", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
