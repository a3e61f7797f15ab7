"""Experiment: the latch also hands back where the policy's action agrees with physics' (|d steer| <= S, |d acc| <= A).
Shielded only, train scenes; prints success / violation / override share per policy."""
import json, os, sys, time
import torch
sys.path.insert(0, "benchmarks")
import shield as bench
from pe_rlhf.transforms.selector import HybridActionSelector
from pe_rlhf.envs import DrivingConfig
from pe_rlhf.evaluation import evaluate, make_policy
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.transforms import SHIELD_PHYSICS
from pe_rlhf.wrappers import SafetyShieldWrapper

S, A = float(os.environ["AGREE_STEER"]), float(os.environ["AGREE_ACC"])
orig = HybridActionSelector._persistent
def patched(self, chosen, obs, acts, value_phy, streak, env):
    out, latch = orig(self, chosen, obs, acts, value_phy, streak, env)
    if S >= 0 and self.persistence == "latch":
        n = len(acts) // 2
        d = (acts[:n] - acts[n:]).abs()
        agree = (d[..., 0] <= S) & (d[..., 1] <= A)
        out = torch.where(chosen & (streak > 0) & agree, torch.ones_like(out), out)
    return out, (~out).long()
HybridActionSelector._persistent = patched

seeds = list(range(int(sys.argv[1]), int(sys.argv[2]) + 1))
out_path = sys.argv[3]
names = sys.argv[4:]
results = json.load(open(out_path)) if os.path.exists(out_path) else {}
config = DrivingConfig(split="train", lane_features=True)
for name in names:
    if name in results: continue
    t = time.time()
    if "=" in name:
        label, run = name.split("=", 1); factory = lambda: bench.agent_policy(run)
    else:
        label = name; factory = lambda: make_policy(name, 0)
    s = evaluate(factory(), seeds, config, name=label, progress=False,
                 wrap_env=lambda env: SafetyShieldWrapper(env, 0.5, physics=IDMMobilPolicy(SHIELD_PHYSICS))).to_dict()
    r = bench.rates(s)
    results[label] = r
    print(f"{label}: {r['success']:.2f} / {r['violation']:.2f} override {r['override_share']:.3f} ({time.time()-t:.0f} s)", flush=True)
    json.dump(results, open(out_path, "w"), indent=1)
