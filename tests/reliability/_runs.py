"""Tiny training runs for the reliability tests: the smoke profile cut to a few seconds."""

from __future__ import annotations

import importlib.util
import json
import os
import random
import subprocess
import sys
from pathlib import Path
from _scripts import SCRIPT_ENV

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "pe_rlhf" / "train.py"
TIMING = ("env_seconds", "update_seconds")  # wall-clock bookkeeping: differs between any two runs

# 25-frame batches, warm-up 50, a checkpoint every 100 frames, no periodic evaluation, no video,
# episodes of at most 50 steps, 2 updates per batch; the learner on the CPU wherever the suite runs (on a GPU
# machine `auto` puts it on CUDA, whose arithmetic changes the traces these tests pin: measured on an H200, the
# mid-takeover resume fixture left its takeover and the synced-copy test compared a CUDA run with a CPU one).
TINY = ["profile=smoke", "optim.device=cpu", "env.horizon=50", "collector.frames_per_batch=25",
        "collector.warmup_steps=50",
        "optim.updates_per_batch=2",
        "eval.every_frames=0", "eval.episodes=1", "eval.video=false", "checkpoint.every_frames=100",
        "checkpoint.keep=2"]


# The replay rows in collection order, for the tests that index them by frame: one uniform buffer. The recipe's
# default (replay_buffer.takeover_share=0.5) keeps takeover rows in a buffer of their own, and nothing in a row says
# which frame it was, so checkpoint_contents returns that layout's takeover rows first, then the agent's (each in
# collection order): enough for the tests that compare two runs' checkpoints whole, not for ``replay[frame]``.
UNIFORM_REPLAY = "replay_buffer.takeover_share=null"

KILL_SEED_VAR = "PE_RLHF_KILL_SEED"


def kill_rng(what: str) -> random.Random:
    """The RNG that picks when a test kills a process: seeded from ``$PE_RLHF_KILL_SEED``, else from a fresh seed,
    printed (pytest shows it with a failure) so that the very kill can be replayed."""
    seed = int(os.environ.get(KILL_SEED_VAR) or random.SystemRandom().randrange(2**31))
    print(f"{what}: kill seed {seed} (replay: {KILL_SEED_VAR}={seed} pytest ...)", flush=True)
    return random.Random(seed)


def load_recipe():
    spec = importlib.util.spec_from_file_location("pe_rlhf_recipe_reliability", RECIPE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def train(out: Path, *overrides: str, resume: bool = False) -> dict:
    """The recipe in this process (call with one torch thread for bit-identical updates)."""
    argv = ["--resume", str(out), *overrides] if resume else [*TINY, *overrides, "--out", str(out)]
    return load_recipe().main(argv)


def start_training(out: Path, *overrides: str) -> subprocess.Popen:
    """The recipe in a child process (one torch thread, headless), output to ``out/stdout.txt``."""
    env = {**os.environ, "PYTHONPATH": SCRIPT_ENV["PYTHONPATH"], "SDL_VIDEODRIVER": "dummy", "OMP_NUM_THREADS": "1"}
    out.mkdir(parents=True, exist_ok=True)
    log = open(out.parent / f"{out.name}.log", "w")  # noqa: SIM115 - the child holds it
    return subprocess.Popen([sys.executable, str(RECIPE), *TINY, *overrides, "--out", str(out)], cwd=ROOT, env=env,
                            stdout=log, stderr=subprocess.STDOUT)


def checkpoint_contents(ckpt: Path) -> dict:
    """Everything a checkpoint holds, loaded: tensors, RNG, state, the replay buffers' contents. The learner's
    buffer is built as the run built it: with ``replay_buffer.takeover_share`` set, its takeover rows then its
    agent's (see :data:`UNIFORM_REPLAY`)."""
    import torch

    from pe_rlhf.algorithms.proxy_q.builders import build_replay_buffer
    from pe_rlhf.algorithms.proxy_q.takeover_replay import TakeoverBalancedReplayBuffer
    from pe_rlhf.runtime.checkpoint import load_checkpoint
    from pe_rlhf.algorithms.proxy_q.config import load_config

    cfg = load_config(ckpt.parents[1] / "config.yaml", apply_profile=False)
    buffers = {"replay": build_replay_buffer(cfg, balanced=True), "warmup": build_replay_buffer(cfg)}
    load_checkpoint(ckpt, modules={}, optimizers={}, replay_buffers=buffers, strict=False, restore_rng_state=False)
    out = {"tensors": torch.load(ckpt / "tensors.pt", weights_only=True),
           "rng": torch.load(ckpt / "rng.pt", weights_only=True),
           "state": json.loads((ckpt / "state.json").read_text())}
    for name, buffer in buffers.items():
        if isinstance(buffer, TakeoverBalancedReplayBuffer):
            out[name] = torch.cat([part[:] for part in (buffer.takeover, buffer.agent) if len(part)])
        else:
            out[name] = buffer[:]
    for k in TIMING:
        out["state"]["counters"].pop(k)
    return out
