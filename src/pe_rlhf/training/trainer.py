"""The PE-RLHF (and HACO) training loop: warm-up, ensemble fit, online collection with takeovers, updates.

Phases, top to bottom in :func:`train`:

1. warm-up: the mentor drives ``collector.warmup_steps`` steps (the transform forces it); the
   transitions, with the env reward, fill a warm-up buffer and, relabelled (the mentor's action
   stands as the agent's), the replay buffer;
2. the Q-ensemble is fitted on the warm-up data (then frozen, or refreshed on a schedule);
3. online: the collector runs the actor inside ``InterventionTransform`` (mentor + physics +
   selector); ``optim.updates_per_batch`` PERLHFLoss updates follow every batch once
   ``collector.learning_starts`` frames are in (with ``optim.async_updates``, at the same ratio in a
   learner thread beside acting: :mod:`pe_rlhf.training.background_updates`; ``collector.realtime_hz``
   holds the env to a steady step rate for a person: :class:`~pe_rlhf.transforms.RealtimePacing`);
4. every ``eval.every_frames``: evaluation on the test split without the mentor; every
   ``checkpoint.every_frames``: a checkpoint (``--resume DIR`` continues from it).

``collector.backend`` picks the collector (:func:`pe_rlhf.training.builders.build_collector`). With
a multi-worker backend the workers own the envs, mentors and transforms, so a resume restarts the
workers' simulated mentors (fatigue, RNG) and sets their transform step counters from the
checkpointed global frame count (no repeated warm-up); everything else (networks, optimisers,
buffers, counters) resumes exactly.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from tqdm import tqdm

from pe_rlhf.evaluation import TorchRLPolicyAdapter, evaluate
from pe_rlhf.modules import EnsembleSchedule, fit_q_ensemble
from pe_rlhf.threads import torch_threads
from pe_rlhf.training import builders
from pe_rlhf.training.steps import batch_metrics, ensemble_transitions, relabel_warmup
from pe_rlhf.transforms import InterventionTransform, RealtimePacing

EVAL_KEYS = ("episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
             "overtake_count")


class Counters:
    """Cumulative training bookkeeping (saved in checkpoints)."""

    def __init__(self):
        self.frames = self.takeover_steps = self.takeover_starts = self.mentor_chosen_steps = 0.0
        self.safety_violations = self.episodes = self.successes = self.updates = 0.0
        self.online_frames = self.env_seconds = self.update_seconds = 0.0

    def add(self, m: dict[str, float], warmup: bool) -> None:
        self.frames += m["steps"]
        self.safety_violations += m["safety_violations"]
        self.episodes += m["episodes"]
        self.successes += m["successes"]
        if not warmup:
            self.online_frames += m["steps"]
            self.takeover_steps += m["takeover_steps"]
            self.takeover_starts += m["takeover_starts"]
            self.mentor_chosen_steps += m["mentor_chosen_steps"]

    def state_dict(self) -> dict:
        return dict(vars(self))

    def load_state_dict(self, state: dict) -> None:
        vars(self).update(state)


def _next_multiple(frames: float, every: int) -> float:
    """The next frame count at which a periodic job runs (never, when ``every`` is 0)."""
    return float("inf") if every <= 0 else (int(frames) // every + 1) * every


def evaluate_actor(actor, cfg, env_config, episodes: int) -> dict:
    """Deterministic evaluation of the actor on the first ``episodes`` seeds of ``eval.split``."""
    from pe_rlhf.envs import scene_seeds

    seeds = scene_seeds(str(cfg.eval.split))[:episodes]
    return evaluate(TorchRLPolicyAdapter(actor), seeds, env_config, progress=False).to_dict()


VIDEO_NAME = "test_episode.gif"
VIDEO_MAX_STEPS = 400


def record_test_video(actor, cfg, env_config, path: Path) -> dict:
    """A GIF of the trained agent (deterministic) on the first ``eval.split`` scene, at most
    ``VIDEO_MAX_STEPS`` steps (40 s of driving); returns where it ended (success, crash, ...)."""
    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.training.video import record_episode_gif

    seed = scene_seeds(str(cfg.eval.split))[0]
    info = record_episode_gif(TorchRLPolicyAdapter(actor), env_config, seed, path, max_steps=VIDEO_MAX_STEPS)
    return {k: info[k] for k in ("path", "steps", "success", "crash_vehicle", "crash_object", "out_of_road")}


def registered_policies() -> list[str]:
    """Names :func:`evaluate_reference` accepts (the evaluation registry, mentors included)."""
    import pe_rlhf.mentors.registry  # noqa: F401
    from pe_rlhf.evaluation import POLICY_FACTORIES

    return list(POLICY_FACTORIES)


def evaluate_reference(policy_name: str, cfg, episodes: int | None = None) -> dict:
    """A registered policy (e.g. ``idm-mobil``) on the same ``eval.split`` seeds as :func:`evaluate_actor`,
    for the comparison table printed after training (``train.py --compare idm-mobil``)."""
    import pe_rlhf.mentors.registry  # noqa: F401  (registers the mentors as evaluation policies)
    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.evaluation import make_policy
    from pe_rlhf.training.config import driving_config

    seeds = scene_seeds(str(cfg.eval.split))[: int(episodes or cfg.eval.episodes)]
    return evaluate(make_policy(policy_name, int(cfg.seed)), seeds, driving_config(cfg), progress=False,
                    name=policy_name).to_dict()


def pacing_log(pacing: RealtimePacing | None, frames: int) -> dict[str, float]:
    """Frame-time columns over the batch's last ``frames`` frames (none when the env is not paced)."""
    if pacing is None:
        return {}
    stats = pacing.frame_stats(last=frames)
    return {"time/frame_ms_mean": stats["frame_ms_mean"], "time/frame_jitter_ms_p95": stats["jitter_ms_p95"],
            "time/frame_jitter_ms_max": stats["jitter_ms_max"]}


def iteration_log(counters: Counters, m: dict, losses: dict, started: float) -> dict[str, float]:
    online = max(counters.online_frames, 1.0)
    log = {
        "env_steps": counters.frames,
        "wall_time": time.time() - started,
        "train/safety_violations_total": counters.safety_violations,
        "train/takeover_rate": m["takeover_steps"] / max(m["steps"], 1.0),
        "train/takeover_count": counters.takeover_starts,
        "train/takeover_data_usage": counters.takeover_steps / online,
        "train/value_takeover_count": counters.mentor_chosen_steps,
        "train/value_takeover_rate": counters.mentor_chosen_steps / max(counters.takeover_steps, 1.0),
        "train/intervention_cost": m["intervention_cost"],
        "train/success_rate_total": counters.successes / max(counters.episodes, 1.0),
        "time/env_seconds": counters.env_seconds,
        "time/update_seconds": counters.update_seconds,
    }
    for k, v in losses.items():
        log[f"loss/{k[5:]}" if k.startswith("loss_") else f"train/{k}"] = v
    return log


def train(cfg, out_dir: Path, logger, checkpoint_dir: Path | None = None, resume: bool = False) -> dict:
    """Run the recipe described by ``cfg``; returns the final evaluation summary dict.

    ``logger`` has ``log(step, metrics)`` (and ``truncate_after`` for resuming). With
    ``checkpoint_dir``, checkpoints are written every ``checkpoint.every_frames``; with ``resume``,
    the newest one there is loaded first and the run continues from its step.
    """
    torch.manual_seed(int(cfg.seed))
    update_threads = torch.get_num_threads()
    with torch_threads(1):
        return _train(cfg, out_dir, logger, checkpoint_dir, resume, update_threads)


def _train(cfg, out_dir, logger, checkpoint_dir, resume: bool, update_threads: int) -> dict:
    from pe_rlhf.training.checkpoint import load_checkpoint, save_checkpoint

    from pe_rlhf.training.config import driving_config

    env_config = driving_config(cfg)
    ensemble = builders.build_q_ensemble(cfg)
    env, mentor = builders.build_local_env(cfg, env_config, ensemble)  # None, None: the workers own them
    actor = builders.build_actor(cfg)
    loss, soft_update = builders.build_loss(cfg, actor)
    optimizers = builders.build_optimizers(cfg, loss)
    replay, warmup_buffer = builders.build_replay_buffer(cfg), builders.build_replay_buffer(cfg)
    schedule = EnsembleSchedule(int(cfg.collector.warmup_steps), int(cfg.selector.refresh_every),
                                int(cfg.selector.warmup_fit_steps), int(cfg.selector.refresh_steps))
    counters = Counters()
    objects = {"modules": {"loss": loss, **({"ensemble": ensemble} if ensemble is not None else {})},
               "optimizers": optimizers, "replay_buffers": {"replay": replay, "warmup": warmup_buffer}}
    transform = builders.find_transform(env, InterventionTransform) if env is not None else None
    pacing = builders.find_transform(env, RealtimePacing) if env is not None else None
    if resume:
        resume_state = load_checkpoint(checkpoint_dir, **objects)
        logger.truncate_after(int(resume_state["step"]) + 1)  # rows after the checkpoint are re-collected
        counters.load_state_dict(resume_state["counters"])
        schedule.load_state_dict(resume_state["schedule"])
        if transform is not None:  # multi-worker backends restart them (see the module docstring)
            transform.total_steps = int(resume_state["transform_steps"])
            if resume_state["mentor"] is not None:
                mentor.load_state_dict(resume_state["mentor"])
    remaining = int(cfg.collector.total_frames) - int(counters.frames)
    updater = builders.build_updater(cfg, loss, optimizers, soft_update, replay, actor, update_threads)
    updates0, update_seconds0 = counters.updates, counters.update_seconds
    collector = builders.build_collector(cfg, env, updater.policy, remaining, ensemble=ensemble,
                                         start_frames=int(counters.frames)) if remaining > 0 else None
    started, losses = time.time(), {}
    next_eval = _next_multiple(counters.frames, int(cfg.eval.every_frames))
    next_ckpt = _next_multiple(counters.frames, int(cfg.checkpoint.every_frames))
    bar = tqdm(total=int(cfg.collector.total_frames), initial=int(counters.frames), desc="PE-RLHF", unit="step")
    t_env = time.time()
    updater.start()  # optim.async_updates: the learner thread (pe_rlhf.training.background_updates)
    for batch in collector or []:
        counters.env_seconds += time.time() - t_env
        if counters.frames >= int(cfg.collector.total_frames):
            break
        warmup = counters.frames < int(cfg.collector.warmup_steps)
        m = batch_metrics(batch)
        counters.add(m, warmup)
        if warmup:
            warmup_buffer.extend(ensemble_transitions(batch).reshape(-1))  # (N, T) with multisync: time last
            batch = relabel_warmup(batch, keep_agent_action=bool(cfg.collector.warmup_gap))
            m["intervention_cost"] = 0.0  # forced mentor driving is no takeover: nothing is charged
        with updater.lock:  # the learner thread samples from it
            replay.extend(batch.reshape(-1))
        fit_steps = schedule.due(int(counters.frames)) if ensemble is not None else 0
        if fit_steps:
            fit_q_ensemble(ensemble, warmup_buffer, steps=fit_steps, batch_size=int(cfg.selector.batch_size),
                           gamma=float(cfg.loss.gamma), lr=float(cfg.selector.lr),
                           target_noise=float(cfg.selector.target_noise), loss=str(cfg.selector.fit_loss),
                           seed=int(cfg.seed))
            ensemble.requires_grad_(False)
            builders.push_ensemble_weights(collector, ensemble)
        backlog = updater.backlog  # updates owed by earlier batches, not run yet: 0 while the learner keeps up
        if counters.frames >= int(cfg.collector.learning_starts):
            updater.notify_frames(int(m["steps"]))  # sync: the updates these frames pay for run here
            losses = updater.latest_losses() or losses
            builders.sync_policy(collector)
        counters.updates = updates0 + updater.updates_done
        counters.update_seconds = update_seconds0 + updater.update_seconds
        metrics = iteration_log(counters, m, losses, started)
        metrics["train/update_backlog"] = float(backlog)
        metrics.update(pacing_log(pacing, int(m["steps"])))
        if counters.frames >= next_eval:
            next_eval = _next_multiple(counters.frames, int(cfg.eval.every_frames))
            with updater.paused():
                summary = evaluate_actor(actor, cfg, env_config, int(cfg.eval.episodes))
            for k in EVAL_KEYS:
                metrics[f"eval/{k}_mean"], metrics[f"eval/{k}_std"] = summary[k]["mean"], summary[k]["std"]
        logger.log(int(counters.frames), metrics)
        bar.update(int(m["steps"]))
        bar.set_postfix(takeover=f"{metrics['train/takeover_rate']:.2f}",
                        violations=int(counters.safety_violations), succ=f"{metrics['train/success_rate_total']:.2f}")
        if checkpoint_dir is not None and counters.frames >= next_ckpt:
            next_ckpt = _next_multiple(counters.frames, int(cfg.checkpoint.every_frames))
            with updater.paused():  # networks, optimisers and counters from one moment
                counters.updates = updates0 + updater.updates_done
                save_checkpoint(checkpoint_dir, step=int(counters.frames), keep=int(cfg.checkpoint.keep), **objects,
                                state={"counters": counters.state_dict(), "schedule": schedule.state_dict(),
                                       "mentor": mentor.state_dict() if mentor is not None else None,
                                       "transform_steps": int(counters.frames) if transform is None
                                       else transform.total_steps})
        t_env = time.time()
    updater.stop()  # async: the updates still owed run first, so the run keeps its update-to-data ratio
    counters.updates = updates0 + updater.updates_done
    counters.update_seconds = update_seconds0 + updater.update_seconds
    bar.close()
    if collector is not None:
        builders.shutdown_collector(collector)
    final = evaluate_actor(actor, cfg, env_config, int(cfg.eval.episodes))
    final["training"] = counters.state_dict()
    torch.save(actor.state_dict(), out_dir / "actor.pt")
    if cfg.eval.video:
        final["video"] = record_test_video(actor, cfg, env_config, out_dir / VIDEO_NAME)
    return final
