"""How often does a run's fitted Q-ensemble pick the safer of the mentor's and the physics' actions?

    python benchmarks/selector_accuracy.py RUN_DIR [RUN_DIR ...] [--scenes 0-19] [--hold 10] [--horizon 40]
        [--epsilons 0 0.5 1.5] [--max-states 300] [--every 10] [--json out.json]
    python benchmarks/selector_accuracy.py --mentors professional adversarial [--value expert|forecast]
        [--epsilon-run E] ...

``--mentors``: no run folder; the recipe's defaults with each mentor and ``selector.value`` (``--value``: a
frozen expert, the packaged one by default), as a PE-RLHF run would start its online phase with.

For each run folder (PE-RLHF recipe; its ``config.yaml`` and the Q-ensemble in its newest checkpoint):
obstacle-blind IDM-MOBIL drives the train scenes as the agent, under the run's own mentor (its
``mentor.name``, seeded from its ``seed``), physics policy (its ``physics.*`` flags) and selector (``epsilon_select``),
so the states are those a PE-RLHF takeover meets. At every ``--every``-th takeover step both candidates
are tried on copies of the simulator (and of the mentor or physics policy): the candidate's action, then
its own driver for the rest of ``--hold`` steps (a takeover lasts at least 10), then IDM-MOBIL that sees
obstacles (0.98 success on the test scenes) for the rest of ``--horizon`` steps (``--continuation own``). With
``--continuation executed`` each candidate's action is followed by what the hybrid would execute instead: the
mentor's action at every step unless the selector (the same values and threshold) prefers physics', so a
candidate is judged by the step it decides, not by a manoeuvre that the selector would cut short. A candidate
*fails* when its copy crashes or leaves the road within the horizon. On the *decisive* states (exactly one
candidate fails) the selector is right when it
picks the other one; reported per ``--epsilons`` value, with "always the mentor" and "always physics" as
references, plus the advantage ``mean_k Q_k(s, a_mentor) - Q_k(s, a_phy)`` on the decisive states split by
which candidate was the safe one (a useful ensemble puts them apart).
"""
from __future__ import annotations

import argparse
import copy
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pe_rlhf.envs import make_gym_env
from pe_rlhf.physics import IDMMobilPolicy, PhysicsConfig
from pe_rlhf.runtime.checkpoint import find_checkpoint, load_checkpoint
from pe_rlhf.runtime.config import driving_config
from pe_rlhf.runtime.world import build_mentor
from pe_rlhf.algorithms.proxy_q.builders import build_physics, build_value_source, epsilon_select
from pe_rlhf.algorithms.proxy_q.config import load_config


def parse_scenes(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def load_run(run: Path):
    cfg = load_config(run / "config.yaml", apply_profile=False)
    ensemble = build_value_source(cfg)
    if ensemble is None:
        raise SystemExit(f"{run}: selector.enabled is false (a HACO run has no ensemble)")
    load_checkpoint(find_checkpoint(run / "checkpoints"), modules={"ensemble": ensemble}, optimizers={},
                    replay_buffers={}, strict=False, restore_rng_state=False)
    return cfg, ensemble.eval()


def fails(env, action, policy, hold: int, horizon: int, oracle: IDMMobilPolicy) -> bool:
    """On a copy of ``env``: ``action``, then ``policy`` (a copy of the candidate's driver) until step
    ``hold``, then the oracle until ``horizon``: did the car crash or leave the road?"""
    sim, policy = copy.deepcopy(env), copy.deepcopy(policy)
    oracle.reset()
    for t in range(horizon):
        a = action if t == 0 else np.asarray(policy(sim) if t < hold else oracle(sim), np.float32)
        _, _, terminated, truncated, info = sim.step(a)
        if terminated or truncated:
            return bool(info.get("crash_vehicle") or info.get("crash_object") or info.get("out_of_road"))
    return False


def fails_executed(env, obs, action, mentor, physics, ensemble, eps: float, hold: int, horizon: int,
                   oracle: IDMMobilPolicy) -> bool:
    """On a copy of ``env``: ``action``, then the hybrid's choice between (copies of) the mentor's and physics'
    actions by ``ensemble`` at threshold ``eps`` until step ``hold``, then the oracle until ``horizon``: did the car
    crash or leave the road?"""
    sim, mentor, physics = copy.deepcopy(env), copy.deepcopy(mentor), copy.deepcopy(physics)
    oracle.reset()
    for t in range(horizon):
        if t == 0:
            a = action
        elif t < hold:
            a_mentor, a_phy = np.asarray(mentor.act(sim), np.float32), np.asarray(physics(sim), np.float32)
            a = a_mentor if advantage(ensemble, obs, a_mentor, a_phy, sim) >= eps else a_phy
        else:
            a = np.asarray(oracle(sim), np.float32)
        obs, _, terminated, truncated, info = sim.step(a)
        if terminated or truncated:
            return bool(info.get("crash_vehicle") or info.get("crash_object") or info.get("out_of_road"))
    return False


def advantage(ensemble, obs, a_mentor, a_phy, env) -> float:
    """``mean_k Q_k(s, a_mentor) - Q_k(s, a_phy)`` (the forecast reads the simulator ``env``)."""
    with torch.no_grad():
        pair = (torch.as_tensor(np.stack([obs, obs])), torch.as_tensor(np.stack([a_mentor, a_phy])))
        q = ensemble.values(*pair, env=env) if getattr(ensemble, "needs_env", False) else ensemble.values(*pair)
    return float((q[:, 0] - q[:, 1]).mean())


def count_events(states: list[tuple]) -> int:
    """Decisive states come in runs (the steps of one approach to an obstacle): how many runs, counting
    states of the same scene at most 10 steps apart as one."""
    events, last = 0, None
    for s in sorted(states, key=lambda s: (s[3], s[4])):
        if last is None or s[3] != last[3] or s[4] - last[4] > 10:
            events += 1
        last = s
    return events


def expert_setup(mentor: str, value: str, epsilon_run: float | None = None):
    """The recipe's defaults with ``mentor`` and ``selector.value=value`` (a frozen expert or the physics
    forecast: nothing to fit), ``selector.epsilon_select=epsilon_run`` when given."""
    extra = [] if epsilon_run is None else [f"selector.epsilon_select={epsilon_run}"]
    cfg = load_config(overrides=[f"mentor.name={mentor}", f"selector.value={value}", *extra])
    return cfg, build_value_source(cfg).eval()


def measure(run: Path | str, args, setup=None) -> dict:
    cfg, ensemble = setup if setup is not None else load_run(run)
    env = make_gym_env(driving_config(cfg))
    mentor, driver, physics = build_mentor(cfg), IDMMobilPolicy(PhysicsConfig()), build_physics(cfg)
    oracle = IDMMobilPolicy(PhysicsConfig(see_obstacles=True))
    eps_run = epsilon_select(cfg)
    states = []  # (advantage, mentor_fails, physics_fails, scene seed, step)
    differences = []  # a_mentor - a_phy at every takeover state
    bar = tqdm(total=args.max_states, desc=str(getattr(run, "name", run)), leave=False)
    for seed in args.scenes:
        obs, _ = env.reset(options={"scene_seed": seed})
        mentor.reset(env)
        driver.reset()
        physics.reset()
        done, step, seen = False, 0, 0
        while not done and len(states) < args.max_states:
            a_agent = np.asarray(driver(env), np.float32)
            decision = mentor.decide(env, a_agent)
            takeover, a_mentor = decision.takeover, decision.action
            executed = a_agent
            if takeover:
                a_mentor = np.asarray(a_mentor, np.float32)
                a_phy = np.asarray(physics(env), np.float32)  # the run's physics policy (its physics.* flags)
                adv = advantage(ensemble, obs, a_mentor, a_phy, env)
                seen += 1
                if seen % args.every == 0 and seen <= args.every * args.max_per_scene:  # every k-th, capped a scene
                    differences.append(a_mentor - a_phy)
                    if args.continuation == "executed":
                        outcome = [fails_executed(env, obs, a, mentor, physics, ensemble, eps_run, args.hold,
                                                  args.horizon, oracle) for a in (a_mentor, a_phy)]
                    else:
                        outcome = [fails(env, a_mentor, mentor.act, args.hold, args.horizon, oracle),
                                   fails(env, a_phy, physics, args.hold, args.horizon, oracle)]
                    states.append((adv, *outcome, seed, step))
                bar.update(1)
                executed = a_mentor if adv >= eps_run else a_phy
            obs, _, terminated, truncated, _ = env.step(executed)
            done, step = terminated or truncated, step + 1
        if len(states) >= args.max_states:
            break
    bar.close()
    decisive = [s for s in states if s[1] != s[2]]
    mentor_safe = [s[0] for s in decisive if not s[1]]
    physics_safe = [s[0] for s in decisive if not s[2]]
    out = {"run": str(run), "mentor": str(cfg.mentor.name), "continuation": args.continuation,
           "selector_tau": float(cfg.selector.get("tau", 0.005)),
           "epsilon_select": eps_run, "takeover_states": len(states), "decisive_states": len(decisive),
           "decisive_events": count_events(decisive), "scenes_driven": len({s[3] for s in states}),
           "mentor_fails": sum(s[1] for s in states), "physics_fails": sum(s[2] for s in states),
           "both_fail": sum(s[1] and s[2] for s in states),
           "always_mentor_right": len(mentor_safe) / max(len(decisive), 1),
           "advantage_median_all": statistics.median(s[0] for s in states) if states else None,
           "mentor_chosen_rate": sum(s[0] >= eps_run for s in states) / max(len(states), 1),
           "mentor_minus_physics_median": np.median(np.stack(differences), 0).tolist() if differences else None,
           "advantage_median_when_mentor_safe": statistics.median(mentor_safe) if mentor_safe else None,
           "advantage_median_when_physics_safe": statistics.median(physics_safe) if physics_safe else None,
           "selector_right": {}}
    for eps in args.epsilons:
        right = sum((s[0] >= eps) == (not s[1]) for s in decisive)
        out["selector_right"][str(eps)] = right / max(len(decisive), 1)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="*", type=Path)
    parser.add_argument("--mentors", nargs="+", default=None, help="no run folder: these mentors with --value")
    parser.add_argument("--value", default="expert",
                        help="selector.value with --mentors (expert | expert:PATH | forecast)")
    parser.add_argument("--scenes", type=parse_scenes, default=parse_scenes("0-19"),
                        help="train scene seeds, e.g. 0-19")
    parser.add_argument("--hold", type=int, default=10, help="steps each candidate drives before the oracle does")
    parser.add_argument("--continuation", choices=("own", "executed"), default="own",
                        help="after each candidate's action: its own driver (own) or the hybrid's choice between "
                             "the mentor's and physics' actions (executed), until --hold")
    parser.add_argument("--horizon", type=int, default=40, help="steps of each counterfactual rollout")
    parser.add_argument("--epsilons", type=float, nargs="+", default=[0.0, 0.5, 1.5])
    parser.add_argument("--max-states", type=int, default=300, help="labelled takeover states per run")
    parser.add_argument("--every", type=int, default=10, help="label every k-th takeover state (1: all of them)")
    parser.add_argument("--max-per-scene", type=int, default=10**9,
                        help="label at most this many states a scene (a car stuck behind an obstacle is taken over "
                             "for hundreds of steps: without a cap one scene fills the sample)")
    parser.add_argument("--epsilon-run", type=float, default=None,
                        help="with --mentors: the threshold the driven takeovers execute with (default: the recipe's)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.every < 1:
        parser.error(f"--every {args.every}: must be at least 1 (1 labels every takeover state)")
    if not args.runs and not args.mentors:
        parser.error("give run folders or --mentors")
    torch.set_num_threads(1)
    results = []
    jobs = [(run, None) for run in args.runs] + [(f"{m} ({args.value})", (m, args.value, args.epsilon_run))
                                               for m in args.mentors or []]
    for run, virtual in jobs:
        t = time.time()
        r = measure(run, args, expert_setup(*virtual) if virtual else None)
        r["seconds"] = time.time() - t
        results.append(r)
        sel = ", ".join(f"eps {k}: {v:.2f}" for k, v in r["selector_right"].items())
        print(f"{run}: {r['takeover_states']} takeover states, {r['decisive_states']} decisive in "
              f"{r['decisive_events']} events "
              f"(mentor fails {r['mentor_fails']}, physics fails {r['physics_fails']}, both {r['both_fail']}); "
              f"mentor chosen at {r['mentor_chosen_rate']:.2f} of them (median advantage {r['advantage_median_all']}, "
              f"median a_mentor - a_phy {r['mentor_minus_physics_median']}); "
              f"right on decisive states: always mentor {r['always_mentor_right']:.2f}, {sel}; median advantage "
              f"when the mentor is safe {r['advantage_median_when_mentor_safe']}, when physics is safe "
              f"{r['advantage_median_when_physics_safe']}", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"args": {k: (str(v) if isinstance(v, Path) else v)
                                                  for k, v in vars(args).items()
                                                  if k != "runs"}, "results": results}, indent=2) + "\n")
    return results


if __name__ == "__main__":
    main()
