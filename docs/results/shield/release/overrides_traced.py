"""Where does the shield override a trained agent? Per step: one-step veto or latch hold, forecasts, speed, action.

A notebook script (it reads the shield's private latch state), run from the repository root:
    PYTHONPATH=src python docs/results/shield/release/overrides_traced.py RUN_DIR 0,1,...,9 OUT.json
"""
import json, sys
import numpy as np, torch
from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.wrappers import SafetyShieldWrapper
sys.path.insert(0, "benchmarks")
from shield import agent_policy

run, scenes, out = sys.argv[1], [int(s) for s in sys.argv[2].split(",")], sys.argv[3]
policy = agent_policy(run)
env = SafetyShieldWrapper(make_gym_env(DrivingConfig(split="train", lane_features=True)))
rows = []
for seed in scenes:
    policy.reset()
    obs, info = env.reset(options={"scene_seed": seed})
    sim = env.unwrapped
    done = False; step = 0
    while not done:
        latched = env.core._latch is not None and bool(env.core._latch.bool().any())
        speed = float(sim.vehicle.speed)
        action = np.asarray(policy(obs, sim), dtype=np.float32)
        pre_rep = float(env.core.selector.q_ensemble.repeated_values(torch.zeros(1, 1), torch.as_tensor(action).reshape(1, 2), env=sim).mean().item()) if latched else float("nan")
        obs, r, term, trunc, info = env.step(action)
        tp, tf = info["policy_time_to_failure"], info["physics_time_to_failure"]
        eps = float(env.core.selector._epsilon(torch.tensor([tf])).item())
        executed = np.asarray(info["shielded_action"], dtype=np.float32)
        rows.append(dict(scene=seed, step=step, speed=speed, steer=float(action[0]), acc=float(action[1]),
                         override=bool(info["shield_override"]), latched_before=latched,
                         one_step_veto=bool(tp - tf < eps), tp=tp, tf=tf, eps=eps, ex_steer=float(executed[0]), ex_acc=float(executed[1]), rep=pre_rep))
        step += 1; done = term or trunc
    ep = [r for r in rows if r["scene"] == seed]
    print(seed, "success", info["success"], "steps", len(ep), "overrides", sum(r["override"] for r in ep),
          "veto", sum(r["override"] and r["one_step_veto"] for r in ep), flush=True)
json.dump(rows, open(out, "w"))
