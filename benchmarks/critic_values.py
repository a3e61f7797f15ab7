"""Where a trained critic's values sit: the agent's rows by how many steps they come before a takeover, against the
rows far from any, and the critic's choice between throttle and brake there, from a run's checkpoint.

    python benchmarks/critic_values.py RUN_DIR [RUN_DIR ...] [--step 30000] [--json out.json]

Reads the checkpoint's replay buffer (``ProxyValueLoss`` runs, ``replay_buffer.takeover_share`` set: the agent's
rows and the takeover rows kept apart) and its critics. An agent row is ``k`` steps before a takeover when, along
its trajectory's agent rows, the ``k``-th one from it leads into a takeover's first step (its next observation is
that step's). Per band of ``k`` (and ``far``: no takeover within 40 steps): rows, the critics' mean value at the
executed action ``Q(s, a)`` and at the actor's ``Q(s, pi(s))``, and ``Q(s, go) - Q(s, brake)`` (the actor's
steering with throttle +0.6 against -0.8). Zero-reward TD gives a row that never leads to a takeover the value 0;
a takeover's ``-B`` carried back along the agent's steps makes them negative, and standing still better than any
road towards a mentor (docs/experiments/learner.md).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

BANDS = ((1, 1), (2, 3), (4, 7), (8, 15), (16, 40), (None, None))  # (None, None): far from any takeover
REACH = 40  # steps walked back from a takeover


def steps_before_takeover(traj: np.ndarray, before: np.ndarray, reach: int = REACH) -> np.ndarray:
    """Per agent row (in collection order), how many of its trajectory's agent rows it is from one that leads into
    a takeover (``before``: 1 on that row), up to ``reach``; a large number where none is within reach."""
    k = np.full(len(traj), np.iinfo(np.int64).max)
    for i in np.flatnonzero(before):
        for d in range(reach):
            j = i - d
            if j < 0 or traj[j] != traj[i]:
                break
            k[j] = min(k[j], d + 1)
    return k


def critic_values(run_dir: Path, step: int) -> dict:
    from pe_rlhf.algorithms.proxy_q import builders
    from pe_rlhf.algorithms.proxy_q.config import load_config
    from pe_rlhf.runtime.checkpoint import load_checkpoint

    cfg = load_config(run_dir / "config.yaml", apply_profile=False)
    loss, _ = builders.build_loss(cfg, builders.build_actor(cfg))
    buffers = {"replay": builders.build_replay_buffer(cfg, balanced=True), "warmup": builders.build_replay_buffer(cfg)}
    load_checkpoint(run_dir / "checkpoints" / f"ckpt_{step:09d}", modules={"loss": loss}, optimizers={},
                    replay_buffers=buffers, strict=False, restore_rng_state=False)
    agent, takeover = buffers["replay"].agent[:], buffers["replay"].takeover[:]

    def q(rows, action):  # the critics' mean value
        td = rows.select(*loss.qvalue_network.in_keys, strict=False).clone(False)
        td.set("action", action)
        values = []
        for params in loss.qvalue_network_params.unbind(0):
            with params.to_module(loss.qvalue_network):
                values.append(loss.qvalue_network(td.clone(False)).get("state_action_value").squeeze(-1))
        return torch.stack(values).mean(0).numpy()

    with torch.no_grad():
        with loss.actor_network_params.to_module(loss.actor_network):
            pi = loss.actor_network(agent.select(*loss.actor_network.in_keys).clone(False)).get("action")
        go, brake = pi.clone(), pi.clone()
        go[:, 1], brake[:, 1] = 0.6, -0.8
        q_exec, q_pi = q(agent, agent["next", "behavior_action"]), q(agent, pi)
        q_gap = q(agent, go) - q(agent, brake)
        starts = takeover["observation"][takeover["next", "intervention_start"].squeeze(-1)].numpy()
        q_take_exec = float(q(takeover, takeover["next", "behavior_action"]).mean())
        q_take_agent = float(q(takeover, takeover["action"]).mean())
    start_keys = {row.tobytes() for row in starts}
    before = np.array([row.tobytes() in start_keys for row in agent["next", "observation"].numpy()])
    k = steps_before_takeover(agent["collector", "traj_ids"].reshape(-1).numpy(), before)
    bands = {}
    for lo, hi in BANDS:
        sel = k > REACH if lo is None else (k >= lo) & (k <= hi)
        label = "far" if lo is None else (f"{lo}" if lo == hi else f"{lo}-{hi}")
        if sel.any():
            bands[label] = {"rows": int(sel.sum()), "q_exec": float(q_exec[sel].mean()), "q_pi": float(q_pi[sel].mean()),
                            "q_go_minus_brake": float(q_gap[sel].mean())}
    return {"run": str(run_dir), "step": step, "agent_rows": len(agent), "takeover_rows": len(takeover),
            "bands": bands, "takeover_q_exec": q_take_exec, "takeover_q_agent": q_take_agent,
            "brake_preferred_share": float(np.mean(q_gap < 0)), "pi_throttle_mean": float(pi[:, 1].mean())}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of ProxyValueLoss runs")
    parser.add_argument("--step", type=int, default=30_000, help="the checkpoint's env step (default 30000)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results = []
    for run in args.runs:
        if not (run / "checkpoints" / f"ckpt_{args.step:09d}").is_dir():
            parser.error(f"{run}: no checkpoint at env step {args.step} (checkpoints/ckpt_{args.step:09d})")
        r = critic_values(run, args.step)
        results.append(r)
        print(f"{run.name} at {args.step}: {r['agent_rows']} agent rows, {r['takeover_rows']} takeover rows "
              f"(Q(s, a_exec) {r['takeover_q_exec']:+.2f}, Q(s, a_agent) {r['takeover_q_agent']:+.2f}); the actor's "
              f"throttle {r['pi_throttle_mean']:+.2f}, brake valued above go on {r['brake_preferred_share']:.2f} of "
              "agent rows")
        print("  steps before a takeover | rows | Q(s, a) | Q(s, pi(s)) | Q(go) - Q(brake)")
        for label, b in r["bands"].items():
            print(f"  {label:>23} | {b['rows']:5d} | {b['q_exec']:+.3f} | {b['q_pi']:+.3f} | {b['q_go_minus_brake']:+.3f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return results


if __name__ == "__main__":
    main()
