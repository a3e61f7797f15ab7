"""Does a Q-ensemble fitted on warm-up data prefer the mentor over obstacle-blind physics where it matters?

    python benchmarks/ensemble_selection.py PHYSICS_FRACTION STEPS FIT_STEPS FIT_LOSS [EPSILON]
    python benchmarks/ensemble_selection.py 0.0 10000 3000 mean    # the README's numbers (and 0.5 ...)

Collects STEPS warm-up steps on train scenes (a PHYSICS_FRACTION of the episodes driven by IDM-MOBIL
without takeovers, the rest by the professional), fits a 5-member ensemble for FIT_STEPS steps on the
executed actions with the env reward, then drives train scenes 0-19 with IDM-MOBIL as the agent under
the professional's takeovers, the selector choosing mentor or physics at each takeover step; prints the
hybrid's success rate, the share of takeover steps executing the mentor, and the advantage percentiles.
"""
import sys, time
import numpy as np, torch
from tensordict import TensorDict
from pe_rlhf.envs import make_gym_env, DrivingConfig, scene_seeds
from pe_rlhf.mentors import make_mentor
from pe_rlhf.physics import IDMMobilPolicy
from pe_rlhf.modules import QEnsemble, fit_q_ensemble, add_next_actions

torch.set_num_threads(2)
phys_frac = float(sys.argv[1]); steps = int(sys.argv[2]); fit = int(sys.argv[3]); fit_loss = sys.argv[4]
eps = float(sys.argv[5]) if len(sys.argv) > 5 else 0.5
rng = np.random.default_rng(0)
env = make_gym_env(DrivingConfig(split="train"))
mentor = make_mentor("professional", 0); phys = IDMMobilPolicy()
train = scene_seeds("train")
O, A, R, N, T, D = [], [], [], [], [], []
t0 = time.time(); n = 0; crashes = 0
while n < steps:
    obs, _ = env.reset(options={"scene_seed": int(rng.choice(train))})
    use_phys = rng.random() < phys_frac
    mentor.reset(env); phys.reset()
    done = False
    while not done and n < steps:
        a = np.asarray(phys(env) if use_phys else mentor.act(env), dtype=np.float32)
        nobs, r, term, trunc, info = env.step(a)
        O.append(obs); A.append(a); R.append(r); N.append(nobs); T.append(term); D.append(term or trunc or n == steps - 1)
        crashes += info.get("crash_object", False) or info.get("crash_vehicle", False)
        obs = nobs; done = term or trunc; n += 1
print(f"collected {n} steps in {time.time()-t0:.0f}s, crashes {crashes}", flush=True)
td = TensorDict({"observation": torch.as_tensor(np.array(O)), "action": torch.as_tensor(np.array(A)),
                 "next": {"observation": torch.as_tensor(np.array(N)), "reward": torch.as_tensor(R, dtype=torch.float32)[:, None],
                          "terminated": torch.as_tensor(T)[:, None], "done": torch.as_tensor(D)[:, None]}}, [n])
add_next_actions(td)
ens = QEnsemble(250, num_members=5, hidden=(256, 256))
t0 = time.time()
info = fit_q_ensemble(ens, td, steps=fit, batch_size=256, loss=fit_loss, seed=0)
print(f"fit {fit} in {time.time()-t0:.0f}s; Q mean on data {ens.values(td['observation'][:2000], td['action'][:2000]).mean():.2f}", flush=True)
# hybrid drive: agent = physics; mentor takes over; selector picks
succ = []; advs = []; chosen = []; tk = 0; tot = 0
for seed in list(range(0, 20)):
    obs, _ = env.reset(options={"scene_seed": seed}); mentor.reset(env); phys.reset()
    done = False
    while not done:
        a_phy = np.asarray(phys(env), dtype=np.float32)
        takeover, m = mentor(env, a_phy)
        a = a_phy
        if takeover:
            q = ens.values(torch.as_tensor(np.stack([obs, obs])), torch.as_tensor(np.stack([m, a_phy]).astype(np.float32)))
            adv = float((q[:, 0] - q[:, 1]).mean().detach()); advs.append(adv)
            pick = adv >= eps; chosen.append(pick); tk += 1
            a = np.asarray(m, dtype=np.float32) if pick else a_phy
        obs, r, term, trunc, info = env.step(a); tot += 1
        done = term or trunc
    succ.append(info["success"])
advs = np.array(advs)
print(f"phys_frac={phys_frac} fit={fit} loss={fit_loss}: hybrid success {np.mean(succ):.2f}; takeover {tk}/{tot}; "
      f"mentor chosen {np.mean(chosen) if chosen else 0:.2f}; adv pcts {np.percentile(advs,[5,50,95,99]).round(2) if len(advs) else None}", flush=True)
