"""The pieces of one PE-RLHF iteration: warm-up relabelling, the ensemble's transitions, the batch's counts and its
row of metrics, the run's counters, the test episode's video (the gradient step itself is every method's:
:func:`pe_rlhf.runtime.update.update`)."""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from pe_rlhf.evaluation import TorchRLPolicyAdapter
from pe_rlhf.modules import add_next_actions
from pe_rlhf.transforms import RealtimePacing
from pe_rlhf.transforms.keys import (BEHAVIOR_ACTION, INTERVENTION, INTERVENTION_COST, INTERVENTION_START,
                                     MENTOR_SELECTED)


def ensemble_transitions(batch: TensorDictBase) -> TensorDictBase:
    """Transitions as the Q-ensemble is fitted on them (the warm-up's): a copy whose ``action`` is the executed
    (mentor's) ``("next", "behavior_action")`` and whose ``("next", "action")`` is the action executed
    at ``s'`` (:func:`~pe_rlhf.modules.add_next_actions`), so ``Q_k`` estimates the value of the
    *driving* policy. (The root ``action`` of a collected batch is the agent's proposal, which the
    mentor overrode during warm-up: fitted on it, ``Q`` would learn that the action does not matter.)

    ``batch``: a flat ``(T,)`` run of consecutive steps from the collector.
    """
    td = batch.select("observation", "next", strict=False).clone()
    td.set("action", td.get(("next", BEHAVIOR_ACTION)).clone())
    return add_next_actions(td)


def relabel_warmup(batch: TensorDictBase) -> TensorDictBase:
    """Warm-up transitions as the loss should see them. The mentor (or the warm-up policy) drove every
    step, so nothing is charged: ``intervention_start`` and ``intervention_cost`` are zeroed (forced
    driving is no takeover).

    The agent's proposals stay as ``action`` and every step stays flagged ``intervention``, so the
    CQL-style gap ranks the mentor's action above the agent's from the first update (the paper's warm-up,
    in which "human mentors continuously control the agent"). (Letting the mentor's action stand as the
    agent's, gap 0, was an option until its measurement lost: docs/experiments/first-30k-runs.md.)

    Reads/writes ``action`` and, under ``next``: ``behavior_action``, ``intervention``,
    ``intervention_start``, ``intervention_cost`` (shapes ``(T, 2)`` / ``(T, 1)``).
    """
    batch = batch.clone(False)
    nxt = batch.get("next")
    nxt.set(INTERVENTION, torch.ones_like(nxt.get(INTERVENTION)))
    nxt.set(INTERVENTION_START, torch.zeros_like(nxt.get(INTERVENTION_START)))
    nxt.set(INTERVENTION_COST, torch.zeros_like(nxt.get(INTERVENTION_COST)))
    return batch


def batch_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Counts over one collected batch (flat ``(T,)``): steps, takeovers, starts, mentor chosen, cost,
    episodes ended by a simulator fault (``sim_error``); ``disturbance_cost`` (sum) only when the batch
    has HAIM-DRL's ``("next", "disturbance_cost")``."""
    nxt = batch.get("next")
    sim_error = nxt.get("sim_error", None)
    intervention = nxt.get(INTERVENTION).squeeze(-1)
    selected = nxt.get(MENTOR_SELECTED).squeeze(-1) & intervention
    done = nxt.get("done").squeeze(-1)
    disturbance = nxt.get("disturbance_cost", None)
    return {
        **({"disturbance_cost": float(disturbance.sum())} if disturbance is not None else {}),
        "steps": float(intervention.numel()),
        "takeover_steps": float(intervention.sum()),
        "takeover_starts": float(nxt.get(INTERVENTION_START).sum()),
        "mentor_chosen_steps": float(selected.sum()),
        "intervention_cost": float(nxt.get(INTERVENTION_COST).sum()),
        "safety_violations": float(nxt.get("cost").sum()),
        "episodes": float(done.sum()),
        "successes": float((nxt.get("success").squeeze(-1) & done).sum()),
        "sim_errors": float(sim_error.sum()) if sim_error is not None else 0.0,
    }


def cut_to(batch, frames: int):
    """``batch`` without its steps past ``frames`` (the run's last batch after a short pending one: the collector
    counts whole batches); a ``(workers, T)`` batch is cut along time, to the least ``T`` that covers ``frames``."""
    if batch.numel() <= frames:
        return batch
    if batch.ndim == 1:
        return batch[:frames]
    return batch[..., : -(-frames // (batch.numel() // batch.shape[-1]))]


class Counters:
    """Cumulative training bookkeeping (saved in checkpoints)."""

    def __init__(self):
        self.frames = self.takeover_steps = self.takeover_starts = self.mentor_chosen_steps = 0.0
        self.safety_violations = self.episodes = self.successes = self.updates = self.sim_errors = 0.0
        self.online_frames = self.env_seconds = self.update_seconds = 0.0

    def add(self, m: dict[str, float], warmup: bool) -> None:
        self.frames += m["steps"]
        self.safety_violations += m["safety_violations"]
        self.episodes += m["episodes"]
        self.successes += m["successes"]
        self.sim_errors += m["sim_errors"]
        if not warmup:
            self.online_frames += m["steps"]
            self.takeover_steps += m["takeover_steps"]
            self.takeover_starts += m["takeover_starts"]
            self.mentor_chosen_steps += m["mentor_chosen_steps"]

    def state_dict(self) -> dict:
        return dict(vars(self))

    def load_state_dict(self, state: dict) -> None:
        vars(self).update(state)


VIDEO_NAME = "test_episode.gif"
VIDEO_MAX_STEPS = 400


def record_test_video(actor, cfg, env_config, path: Path, logger=None, step: int = 0) -> dict:
    """A GIF of the trained agent (deterministic) on the first ``eval.split`` scene, at most
    ``VIDEO_MAX_STEPS`` steps (40 s of driving), also sent to ``logger.log_video`` when the logger has
    one (``eval/test_episode`` at ``step``); returns where it ended (success, crash, ...)."""
    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.runtime.video import record_episode_gif

    seed = scene_seeds(str(cfg.eval.split))[0]
    log_video = getattr(logger, "log_video", None)
    info = record_episode_gif(TorchRLPolicyAdapter(actor), env_config, seed, path, max_steps=VIDEO_MAX_STEPS,
                              keep_video=log_video is not None)
    if log_video is not None:
        log_video("eval/test_episode", info["video"], step=step)
    return {k: info[k] for k in ("path", "steps", "success", "crash_vehicle", "crash_object", "out_of_road")}


def pacing_log(pacing: RealtimePacing | None, frames: int) -> dict[str, float]:
    """Frame-time columns over the batch's last ``frames`` frames (none when the env is not paced)."""
    if pacing is None:
        return {}
    stats = pacing.frame_stats(last=frames)
    return {"time/frame_ms_mean": stats["frame_ms_mean"], "time/frame_jitter_ms_p95": stats["jitter_ms_p95"],
            "time/frame_jitter_ms_max": stats["jitter_ms_max"]}


def iteration_log(counters: Counters, m: dict, losses: dict) -> dict[str, float]:
    online = max(counters.online_frames, 1.0)
    log = {
        "env_steps": counters.frames,
        "train/safety_violations_total": counters.safety_violations,
        "train/takeover_rate": m["takeover_steps"] / max(m["steps"], 1.0),
        "train/takeover_count": counters.takeover_starts,
        "train/takeover_data_usage": counters.takeover_steps / online,
        "train/value_takeover_count": counters.mentor_chosen_steps,
        "train/value_takeover_rate": counters.mentor_chosen_steps / max(counters.takeover_steps, 1.0),
        "train/intervention_cost": m["intervention_cost"],
        "train/success_rate_total": counters.successes / max(counters.episodes, 1.0),
        "train/sim_errors_total": counters.sim_errors,
        "time/env_seconds": counters.env_seconds,
        "time/update_seconds": counters.update_seconds,
    }
    if "disturbance_cost" in m:  # HAIM-DRL
        log["train/disturbance_cost"] = m["disturbance_cost"]
    for k, v in losses.items():
        log[f"loss/{k[5:]}" if k.startswith("loss_") else f"train/{k}"] = v
    return log
