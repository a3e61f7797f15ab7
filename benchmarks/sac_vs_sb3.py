"""End-to-end env steps/s of our SAC recipe (``recipes/sac_rs``) vs stable-baselines3's SAC, same run.

Both train SAC on the same env config (the recipe's ``env`` group, overridable), from the same seed, with
the same hyper-parameters: the recipe's lr, gamma, tau, alpha init, target entropy (-dim A), twin critics,
actor and critics of ``loss.hidden`` (256x256), replay buffer of ``learning_starts + steps`` transitions,
batch ``--batch`` (1024, drawn uniformly with replacement by both, so it may exceed the first updates'
buffer), one gradient step per env step. Before ``--learning-starts`` both act uniformly at
random (SB3's habit; ours through ``collector.init_random_frames``). The timed window is the ``--steps`` env
steps after learning starts, each with its update:

- ours: :class:`pe_rlhf.runtime.run.Run` over :class:`pe_rlhf.algorithms.baselines.loop.BaselineLearner` as the recipe
  runs it (Collector, ``frames_per_batch`` steps then as many updates, tracker, ``metrics.csv`` rows, progress
  bar), from the end of the iteration
  at frame L to the end of the one at L + steps; no evaluation or checkpoint (the recipe's are periodic
  and would be the same for any learner). Acting runs on 1 thread, updates on ``--threads`` (the recipe's
  own choice, :mod:`pe_rlhf.threads`).
- ours_bf16: the same with ``optim.precision=bf16`` (:mod:`pe_rlhf.modules.precision`: bf16 autocast in the
  updates, fp32 weights, optimiser state and network outputs); SB3 runs in fp32, its only mode.
- SB3: ``SAC("MlpPolicy", make_gym_env(config), train_freq=1, gradient_steps=1, ...).learn(L + steps)``,
  from the return of ``collect_rollouts`` at step L to the end of ``learn``; acting and updates on
  ``--threads`` (SB3 does not change torch's thread count).

Each time is split into ``sim`` (``DrivingEnv.step``/``reset`` themselves, the same code in both),
``collect`` (the rest of acting: policy forward, wrappers, collector / rollout loop, buffer writes in SB3),
``update`` (our ``learner.learn``: buffer extend, sampling and updates; SB3's ``train``) and ``other``
(the rest of the loop: our tracker and logging, SB3's bookkeeping). The three run back to back in each
round, the order alternating (these machines are shared and noisy); the comparison is the median over
rounds of each one's steps/s, and the median of the per-round ratios ours / SB3 (and ours_bf16 / SB3). Each
``--threads`` count
gets its own rounds. ``--update-variants R`` then times one update alone (R interleaved rounds): ours,
ours with TorchRL's ``vmap`` over the critics, ours in bf16, SB3 in fp32 and bf16, at ``--batch`` and at batch 16 (the
fixed cost of an update); ``--cprofile N`` prints the top N functions of one more run of each.

    python benchmarks/sac_vs_sb3.py [--steps 2000] [--rounds 3] [--learning-starts 1000] [--batch 1024]
        [--threads N [N ...]] [--seed 0] [--json out.json] [--update-variants R] [--cprofile N]
        [group.key=value ...]

Needs the ``bench`` extra (``pip install -e '.[bench]'``: stable-baselines3).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from pe_rlhf.threads import torch_threads

RATIO_TARGET = 1.3
METHODS = ("ours", "ours_bf16", "sb3")  # ours_bf16: the same recipe with optim.precision=bf16


# --------------------------------------------------------------------------- timing helpers


class SimTimer:
    """Seconds spent inside ``DrivingEnv.step`` / ``reset`` (patched on the class while active)."""

    def __init__(self):
        self.seconds, self.steps, self.resets = 0.0, 0, 0

    def snapshot(self) -> tuple[float, int, int]:
        return self.seconds, self.steps, self.resets

    @contextlib.contextmanager
    def patch(self):
        from pe_rlhf.envs.driving_env import DrivingEnv

        step, reset = DrivingEnv.step, DrivingEnv.reset

        def timed_step(env, action):
            t = time.perf_counter()
            try:
                return step(env, action)
            finally:
                self.seconds += time.perf_counter() - t
                self.steps += 1

        def timed_reset(env, **kwargs):
            t = time.perf_counter()
            try:
                return reset(env, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t
                self.resets += 1

        DrivingEnv.step, DrivingEnv.reset = timed_step, timed_reset
        try:
            yield self
        finally:
            DrivingEnv.step, DrivingEnv.reset = step, reset


def window(total_s: float, collect_s: float, update_s: float, sim: tuple, sim0: tuple, steps: int,
           updates: int) -> dict:
    """One run's timed window: totals, the split (seconds and ms per env step) and steps/s."""
    sim_s, sim_steps, resets = (a - b for a, b in zip(sim, sim0))
    split = {"sim": sim_s, "collect": collect_s - sim_s, "update": update_s,
             "other": total_s - collect_s - update_s}
    return {"steps": steps, "updates": updates, "sim_steps": sim_steps, "resets": resets, "seconds": total_s,
            "steps_per_s": steps / total_s, "split_s": split,
            "split_ms_per_step": {k: 1e3 * v / steps for k, v in split.items()}}


# --------------------------------------------------------------------------- the two runs


def recipe_config(args):
    from pe_rlhf.algorithms.baselines import load_baseline_config

    L, n = args.learning_starts, args.steps
    overrides = [f"seed={args.seed}", f"collector.total_frames={L + n}", f"collector.learning_starts={L}",
                 f"collector.init_random_frames={L}", f"collector.frames_per_batch={args.frames_per_batch}",
                 f"optim.updates_per_batch={args.frames_per_batch}", f"replay_buffer.batch_size={args.batch}",
                 f"replay_buffer.size={L + n}", "eval.every_frames=0", "checkpoint.every_frames=0",
                 *args.overrides]
    return load_baseline_config("sac_rs", overrides=overrides)


def run_ours(cfg, seed: int, sim: SimTimer) -> dict:
    """The recipe's loop (:class:`~pe_rlhf.runtime.run.Run` over :class:`BaselineLearner`), timed from frame L
    to L + steps."""
    from pe_rlhf.algorithms.baselines.loop import BaselineLearner
    from pe_rlhf.runtime.metrics_logger import MetricsLogger
    from pe_rlhf.runtime.run import Run
    from pe_rlhf.threads import torch_threads

    L, end = int(cfg.collector.learning_starts), int(cfg.collector.total_frames)
    cfg.seed = seed
    marks = {}
    with tempfile.TemporaryDirectory() as tmp, MetricsLogger(tmp) as logger:
        torch.manual_seed(seed)  # as train_baseline does
        run = Run(cfg, BaselineLearner(cfg, Path(tmp)), logger, None, total=end, eval_every=0, checkpoint_every=0)
        after_batch = run.after_batch

        def timed_after_batch(row, before):
            after_batch(row, before)
            if run.progress in (L, end):
                marks[run.progress] = (time.perf_counter(), dict(run.seconds), sim.snapshot())

        run.after_batch = timed_after_batch
        run.finish = lambda out_dir: {}  # no final evaluation: only the window counts
        with torch_threads(1):
            run.train(Path(tmp))
    (t0, s0, sim0), (t1, s1, sim1) = marks[L], marks[end]
    return window(t1 - t0, s1["env"] - s0["env"], s1["update"] - s0["update"], sim1, sim0, end - L, end - L)


def make_sb3(cfg, seed: int):
    """SB3's SAC with the recipe's hyper-parameters on ``make_gym_env(config)``."""
    from stable_baselines3 import SAC

    from pe_rlhf.envs import make_gym_env
    from pe_rlhf.runtime.config import driving_config

    lc = cfg.loss
    return SAC("MlpPolicy", make_gym_env(driving_config(cfg)), learning_rate=float(cfg.optim.lr),
               buffer_size=int(cfg.replay_buffer.size), learning_starts=int(cfg.collector.learning_starts),
               batch_size=int(cfg.replay_buffer.batch_size), tau=float(lc.tau), gamma=float(lc.gamma), train_freq=1,
               gradient_steps=1, ent_coef=f"auto_{float(lc.alpha_init)}",
               target_entropy="auto" if lc.target_entropy == "auto" else float(lc.target_entropy),
               policy_kwargs={"net_arch": list(lc.hidden), "n_critics": int(lc.num_qvalue_nets)},
               seed=seed, device="cpu", verbose=0)


def run_sb3(cfg, seed: int, sim: SimTimer) -> dict:
    """:func:`make_sb3` learning for L + steps env steps, timed from step L."""
    from tqdm import tqdm

    L, end = int(cfg.collector.learning_starts), int(cfg.collector.total_frames)
    model = make_sb3(cfg, seed)
    seconds = {"collect": 0.0, "update": 0.0, "updates": 0}
    marks = {}
    bar = tqdm(total=end, desc="SB3 SAC", unit="step", mininterval=1.0)
    collect_rollouts, train = model.collect_rollouts, model.train

    def timed_collect(*a, **kw):
        t = time.perf_counter()
        out = collect_rollouts(*a, **kw)
        seconds["collect"] += time.perf_counter() - t
        bar.update(model.num_timesteps - bar.n)
        if model.num_timesteps == L:
            marks[L] = (time.perf_counter(), dict(seconds), sim.snapshot())
        return out

    def timed_train(*a, **kw):
        t = time.perf_counter()
        out = train(*a, **kw)
        seconds["update"] += time.perf_counter() - t
        seconds["updates"] += 1
        return out

    model.collect_rollouts, model.train = timed_collect, timed_train
    try:
        model.learn(total_timesteps=end)
        marks[end] = (time.perf_counter(), dict(seconds), sim.snapshot())
    finally:
        bar.close()
    (t0, s0, sim0), (t1, s1, sim1) = marks[L], marks[end]
    return window(t1 - t0, s1["collect"] - s0["collect"], s1["update"] - s0["update"], sim1, sim0, end - L,
                  s1["updates"] - s0["updates"])


def run_ours_bf16(cfg, seed: int, sim: SimTimer) -> dict:
    """Our recipe with ``optim.precision=bf16`` (bf16 autocast in the updates; SB3 stays fp32, its default)."""
    cfg.optim.precision = "bf16"
    return run_ours(cfg, seed, sim)


RUNNERS = {"ours": run_ours, "ours_bf16": run_ours_bf16, "sb3": run_sb3}


# --------------------------------------------------------------------------- reporting


def other_jobs() -> list[str]:
    """Command lines of other training or test processes (they share the cores being measured)."""
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        with contextlib.suppress(OSError):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            if ("train.py" in cmd or "pytest" in cmd or "benchmarks/" in cmd) and "python" in cmd:
                found.append(cmd[:200])
    return found


def load() -> dict:
    return {"loadavg_1min": os.getloadavg()[0], "other_jobs": len(other_jobs())}


def machine_info() -> dict:
    import stable_baselines3
    import torchrl

    return {"cpu_count": os.cpu_count(), "cpus_usable": len(os.sched_getaffinity(0)),
            "default_torch_threads": torch.get_num_threads(), "loadavg": os.getloadavg(), "other_jobs": other_jobs(),
            "python": platform.python_version(), "torch": torch.__version__, "torchrl": torchrl.__version__,
            "stable_baselines3": stable_baselines3.__version__, "platform": platform.platform()}


def summarise(rounds: list[dict]) -> dict:
    out = {}
    for m in METHODS:
        runs = [r[m] for r in rounds]
        sps = [run["steps_per_s"] for run in runs]
        out[m] = {"steps_per_s_median": statistics.median(sps), "steps_per_s_min": min(sps),
                  "steps_per_s_max": max(sps),
                  "split_ms_per_step_median": {k: statistics.median(run["split_ms_per_step"][k] for run in runs)
                                               for k in runs[0]["split_ms_per_step"]}}
    for name, m in (("ratio", "ours"), ("ratio_bf16", "ours_bf16")):
        ratios = [r[m]["steps_per_s"] / r["sb3"]["steps_per_s"] for r in rounds]
        out[name] = {"median_of_rounds": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
                     "of_medians": out[m]["steps_per_s_median"] / out["sb3"]["steps_per_s_median"],
                     "per_round": ratios, "target": RATIO_TARGET}
    return out


def markdown(summary: dict, threads: int) -> str:
    names = {"ours": "ours (recipes/sac_rs)", "ours_bf16": "ours, optim.precision=bf16", "sb3": "SB3 SAC (fp32)"}
    header = (f"| {threads} torch thread(s) | env-steps/s (median) | min-max | sim ms | collect ms | update ms "
              "| other ms |")
    lines = [header, "|---|---|---|---|---|---|---|"]
    for m in METHODS:
        s, ms = summary[m], summary[m]["split_ms_per_step_median"]
        lines.append(f"| {names[m]} | {s['steps_per_s_median']:.1f} | {s['steps_per_s_min']:.1f}-"
                     f"{s['steps_per_s_max']:.1f} | {ms['sim']:.1f} | {ms['collect']:.1f} | {ms['update']:.1f} "
                     f"| {ms['other']:.1f} |")
    lines.append("")
    for key, label in (("ratio", "ours / SB3"), ("ratio_bf16", "ours bf16 / SB3 fp32")):
        r = summary[key]
        lines.append(f"{label}: x{r['median_of_rounds']:.2f} (median of rounds; range {r['min']:.2f}-"
                     f"{r['max']:.2f}; of medians x{r['of_medians']:.2f}); target >= x{RATIO_TARGET}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- where the update's time goes


def _random_transitions(n: int, dim: int):
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(0)
    false = torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict({"observation": torch.rand(n, dim, generator=g) * 2 - 1,
                       "action": torch.rand(n, 2, generator=g) * 2 - 1,
                       "next": {"observation": torch.rand(n, dim, generator=g) * 2 - 1,
                                "reward": torch.randn(n, 1, generator=g), "cost": torch.zeros(n, 1), "done": false,
                                "terminated": false}}, [n])


def update_candidates(cfg) -> dict:
    """``{name: one update}`` on the same random transitions: ours as the recipe runs it (TorchRL's
    ``deactivate_vmap``: the critics in a loop), ours with ``vmap`` (TorchRL's default), ours in bf16
    (``optim.precision=bf16``), SB3's ``train(1)`` in fp32 and under bf16 autocast."""
    from stable_baselines3.common.logger import configure

    from pe_rlhf.algorithms.baselines.algorithms import SACLearner
    from pe_rlhf.runtime.update import update
    from pe_rlhf.runtime.world import obs_dim

    dim = obs_dim(cfg)
    data = _random_transitions(min(3000, int(cfg.replay_buffer.size)), dim)
    torch.manual_seed(0)
    ours, vmapped = SACLearner(cfg, dim, lagrangian=False), SACLearner(cfg, dim, lagrangian=False)
    ours.replay.extend(data)
    vmapped.replay = ours.replay
    vmapped.loss.deactivate_vmap = False  # as SACLoss(..., deactivate_vmap=False), TorchRL's default, builds it
    vmapped.loss._make_vmap()
    sb3 = make_sb3(cfg, seed=0)
    sb3.set_logger(configure(None, [""]))
    for row in data:
        sb3.replay_buffer.add(row["observation"][None].numpy(), row["next", "observation"][None].numpy(),
                              row["action"][None].numpy(), row["next", "reward"].numpy(), row["next", "done"].numpy(),
                              [{}])

    def ours_update(learner, precision="fp32"):
        return lambda: update(learner.loss, learner.optimizers, learner.soft_update, learner.replay.sample(),
                              cfg.optim.max_grad_norm, precision)

    def bf16(step):
        def run():
            with torch.autocast("cpu", dtype=torch.bfloat16):
                step()
        return run

    batch = int(cfg.replay_buffer.batch_size)
    return {"ours": ours_update(ours), "ours_vmap": ours_update(vmapped), "ours_bf16": ours_update(ours, "bf16"),
            "sb3": lambda: sb3.train(1, batch), "sb3_bf16": bf16(lambda: sb3.train(1, batch))}


def update_variants(args, rounds: int) -> dict:
    """Median ms of one update alone (no env), the candidates interleaved (order reversed every other round),
    at ``--batch`` and at batch 16 (the fixed cost of an update)."""
    out = {}
    for batch, reps in ((args.batch, 5), (16, 20)):
        steps = update_candidates(recipe_config(argparse.Namespace(**{**vars(args), "batch": batch})))
        for step in steps.values():
            for _ in range(3):
                step()
        ms = {name: [] for name in steps}
        for r in range(rounds):
            for name in (list(steps) if r % 2 == 0 else list(steps)[::-1]):
                times = []
                for _ in range(reps):
                    t = time.perf_counter()
                    steps[name]()
                    times.append(time.perf_counter() - t)
                ms[name].append(1e3 * statistics.median(times))
        out[str(batch)] = {name: {"ms_median": statistics.median(v), "ms_per_round": v,
                                  "sb3_over_this": statistics.median(b / a for a, b in zip(v, ms["sb3"]))}
                           for name, v in ms.items()}
        print(f"one update, batch {batch} ({rounds} rounds x {reps}): " + ", ".join(
            f"{name} {r['ms_median']:.1f} ms (sb3/this x{r['sb3_over_this']:.2f})"
            for name, r in out[str(batch)].items()), flush=True)
    return out


def profile_runs(args, sim: SimTimer, top: int) -> None:
    """One more run of each under cProfile (all of it, warm-up included): the top functions by own time."""
    import cProfile
    import pstats

    for m in METHODS:
        prof = cProfile.Profile()
        prof.enable()
        RUNNERS[m](recipe_config(args), args.seed, sim)
        prof.disable()
        print(f"\n== cProfile: {m} (top {top} by own time) ==")
        pstats.Stats(prof).sort_stats("tottime").print_stats(top)


def compare(args, threads: int, sim: SimTimer) -> dict:
    """``--rounds`` rounds of both runs on ``threads`` torch threads (then the optional profiles)."""
    rounds = []
    with torch_threads(threads):
        for r in range(args.rounds):
            order = METHODS if r % 2 == 0 else METHODS[::-1]
            result = {}
            for m in order:
                result[m] = RUNNERS[m](recipe_config(args), args.seed + r, sim)
                result[m]["load_after"] = load()
                print(f"{threads} thread(s), round {r}: {m:9s} {result[m]['steps_per_s']:6.1f} env-steps/s  "
                      + " ".join(f"{k} {v:.1f}" for k, v in result[m]["split_ms_per_step"].items())
                      + f" ms/step (load {result[m]['load_after']['loadavg_1min']:.2f}, "
                      f"{result[m]['load_after']['other_jobs']} other jobs)", flush=True)
            rounds.append({"order": list(order), "seed": args.seed + r, **result})
        out = {"summary": summarise(rounds), "rounds": rounds}
        print(markdown(out["summary"], threads), flush=True)
        if args.update_variants:
            out["update_variants"] = update_variants(args, args.update_variants)
        if args.cprofile:
            profile_runs(args, sim, args.cprofile)
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="recipe config overrides, e.g. env.traffic_density=0.3")
    parser.add_argument("--steps", type=int, default=2000, help="timed env steps after learning starts")
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--frames-per-batch", type=int, default=100, help="ours: env steps per iteration")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[torch.get_num_threads()],
                        help="torch intra-op thread counts, each compared in its own rounds")
    parser.add_argument("--seed", type=int, default=0, help="round r uses seed + r (the same for both)")
    parser.add_argument("--json", default=None, help="write config, rounds and summary here")
    parser.add_argument("--update-variants", type=int, default=0, metavar="ROUNDS",
                        help="then time one update alone: ours, ours with vmap, ours in bf16, SB3 (fp32, bf16)")
    parser.add_argument("--cprofile", type=int, default=0, metavar="N",
                        help="then profile one more run of each and print the top N functions")
    args = parser.parse_args(argv)
    fpb = args.frames_per_batch
    if args.learning_starts % fpb or args.steps % fpb or args.steps <= 0:
        parser.error("--learning-starts and --steps must be multiples of --frames-per-batch (ours collects whole "
                     "batches), --steps > 0")
    cfg = recipe_config(args)  # validated once, before anything runs
    before, sim = machine_info(), SimTimer()
    with sim.patch():
        by_threads = {str(t): compare(args, t, sim) for t in args.threads}
    from pe_rlhf.runtime.config import to_container

    out = {"args": vars(args), "recipe_config": to_container(cfg), "machine_before": before,
           "machine_after": machine_info(), "threads": by_threads}
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
