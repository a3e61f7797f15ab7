"""The PE-RLHF (and HACO) training loop: warm-up, ensemble fit, online collection with takeovers, updates.

Phases, top to bottom in :func:`train`:

1. warm-up: the mentor (or, with ``collector.warmup_policy``, the trained actor of an earlier run: the
   expert-policy warm-up) drives ``collector.warmup_steps`` steps (the transform forces it); the
   transitions, with the env reward, fill a warm-up buffer and, relabelled
   (:func:`~pe_rlhf.training.steps.relabel_warmup`), the replay buffer;
2. the Q-ensemble is fitted on the warm-up data (then frozen, or refreshed on a schedule);
3. online: the collector runs the actor inside ``InterventionTransform`` (mentor + physics +
   selector); ``optim.updates_per_batch`` PERLHFLoss updates follow every batch once
   ``collector.learning_starts`` frames are in (with ``optim.async_updates``, at the same ratio in a
   learner thread beside acting: :mod:`pe_rlhf.training.background_updates`; ``collector.realtime_hz``
   holds the env to a steady step rate for a person: :class:`~pe_rlhf.transforms.RealtimePacing`);
4. every ``eval.every_frames``: evaluation on the test split without the mentor; every
   ``checkpoint.every_frames``: a checkpoint (``--resume DIR`` continues from it).

What a run survives: each collected batch is journaled (:mod:`pe_rlhf.training.journal`) before
it is used, and with the ``single`` backend each episode that ends inside the batch being collected
is written at once (:mod:`pe_rlhf.training.episode_journal`), so ``--resume`` after a kill replays
the batches since the checkpoint with the RNG states they arrived with, then trains on the
collected batch's steps up to its last finished episode as a short batch, and loses only the steps
of the episode in progress since the batch began (multi-worker backends: the batch being collected);
a non-finite loss, gradient or parameter stops updates with a ``FloatingPointError`` naming it,
after a checkpoint of everything collected; a mentor's disconnect (a person's window closed,
gamepad unplugged: ``disconnects``) triggers a checkpoint at the end of that batch; the run ends
with a checkpoint of its last frame; ``train/sim_errors_total`` counts episodes the simulator's
faults ended (:mod:`pe_rlhf.envs.driving_env`).

A checkpoint taken while collecting (``single`` backend) holds the collection in progress
(:mod:`pe_rlhf.training.collection_state`: the episode, the takeover, the selector's veto count, the
collector's carrier), so ``--resume`` from it with no journal after it (a run's folder kept at that
checkpoint) continues bit-identically to the run that went on; after a kill, the journal's batches are
replayed and collection starts a fresh episode.

``collector.backend`` picks the collector (:func:`pe_rlhf.training.builders.build_collector`). With
a multi-worker backend the workers own the envs, mentors and transforms, so a resume restarts the
workers' simulated mentors (fatigue, RNG) and sets their transform step counters from the
checkpointed global frame count (no repeated warm-up); everything else (networks, optimisers,
buffers, counters) resumes exactly.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from tqdm import tqdm

from pe_rlhf.evaluation import TorchRLPolicyAdapter, evaluate
from pe_rlhf.modules import EnsembleSchedule
from pe_rlhf.objectives import fit_q_ensemble
from pe_rlhf.threads import torch_threads
from pe_rlhf.training import builders
from pe_rlhf.runtime.checkpoint import capture_rng, restore_rng
from pe_rlhf.training.collection_state import capture_collection, restore_collection
from pe_rlhf.training.config import algorithm_name, method_name
from pe_rlhf.training.steps import batch_metrics, ensemble_transitions, relabel_warmup
from pe_rlhf.transforms import InterventionTransform, RealtimePacing

if TYPE_CHECKING:
    from pe_rlhf.training.journal import JournalEntry

EVAL_KEYS = ("episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
             "overtake_count")


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


def next_multiple(frames: float, every: int) -> float:
    """The next frame count at which a periodic job runs (never, when ``every`` is 0)."""
    return float("inf") if every <= 0 else (int(frames) // every + 1) * every


def evaluate_actor(actor, cfg, env_config, episodes: int) -> dict:
    """Deterministic evaluation of the actor on the first ``episodes`` seeds of ``eval.split``."""
    from pe_rlhf.envs import scene_seeds

    seeds = scene_seeds(str(cfg.eval.split))[:episodes]
    return evaluate(TorchRLPolicyAdapter(actor), seeds, env_config, progress=False).to_dict()


VIDEO_NAME = "test_episode.gif"
VIDEO_MAX_STEPS = 400


def record_test_video(actor, cfg, env_config, path: Path, logger=None, step: int = 0) -> dict:
    """A GIF of the trained agent (deterministic) on the first ``eval.split`` scene, at most
    ``VIDEO_MAX_STEPS`` steps (40 s of driving), also sent to ``logger.log_video`` when the logger has
    one (``eval/test_episode`` at ``step``); returns where it ended (success, crash, ...)."""
    from pe_rlhf.envs import scene_seeds
    from pe_rlhf.training.video import record_episode_gif

    seed = scene_seeds(str(cfg.eval.split))[0]
    log_video = getattr(logger, "log_video", None)
    info = record_episode_gif(TorchRLPolicyAdapter(actor), env_config, seed, path, max_steps=VIDEO_MAX_STEPS,
                              keep_video=log_video is not None)
    if log_video is not None:
        log_video("eval/test_episode", info["video"], step=step)
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
        "train/sim_errors_total": counters.sim_errors,
        "time/env_seconds": counters.env_seconds,
        "time/update_seconds": counters.update_seconds,
    }
    if "disturbance_cost" in m:  # HAIM-DRL
        log["train/disturbance_cost"] = m["disturbance_cost"]
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
    run = _Run(cfg, logger, checkpoint_dir, update_threads)
    journaled, pending = run.resume() if resume else ([], None)
    if resume and run.done:  # otherwise the re-evaluation below looks like training that did nothing
        total = int(cfg.collector.total_frames)
        print(f"{out_dir}: the run was already complete ({int(run.counters.frames)} of {total} frames); "
              "evaluating it again (final_eval.json, actor.pt and the plots are rewritten)", flush=True)
    try:
        run.start()
        for entry in journaled:  # the killed run's batches since its checkpoint, as it processed them
            if run.done:
                break
            restore_rng(entry.rng)
            run.process(entry.batch, journaled=True)
            run.restore_actors(entry.state)
        if pending is not None and not run.done:  # its batch up to the last finished episode: a short batch
            restore_rng(pending.rng)
            run.restore_actors(pending.state)  # first: journaled with it, and a checkpoint in process() saves it
            run.process(pending.batch)
        run.collect()
    except FloatingPointError as e:  # a non-finite loss, gradient or parameter: keep the data, then stop
        raise run.stop_on_error(e) from e
    finally:
        run.shutdown_collector()
    return run.finish(out_dir)


class _Run:
    """One training run: its objects, and the work done on each batch, collected or replayed from the
    journal on ``--resume`` (:mod:`pe_rlhf.training.journal`)."""

    def __init__(self, cfg, logger, checkpoint_dir: Path | None, update_threads: int):
        from pe_rlhf.training.config import driving_config
        from pe_rlhf.training.episode_journal import PendingEpisodesJournal
        from pe_rlhf.training.journal import BatchJournal

        self.cfg, self.logger, self.checkpoint_dir = cfg, logger, checkpoint_dir
        self.env_config = driving_config(cfg)
        self.ensemble = builders.build_q_ensemble(cfg)
        self.env, self.mentor = builders.build_local_env(cfg, self.env_config, self.ensemble)  # None: workers own them
        self.actor = builders.build_actor(cfg)
        self.loss, soft_update = builders.build_loss(cfg, self.actor)
        self.device = builders.learner_device(cfg)  # None: the CPU, acting with the learner's actor
        if self.device is not None:
            self.loss.to(self.device)  # actor, critics, targets (the actor's parameters are the loss's)
        self.optimizers = builders.build_optimizers(cfg, self.loss)
        self.replay, self.warmup_buffer = builders.build_replay_buffer(cfg), builders.build_replay_buffer(cfg)
        fitted = cfg.selector.enabled and builders.value_is_fitted(cfg)  # an expert is frozen: never fitted
        self.schedule = EnsembleSchedule(int(cfg.collector.warmup_steps), int(cfg.selector.refresh_every) if fitted else 0,
                                         int(cfg.selector.warmup_fit_steps) if fitted else 0,
                                         int(cfg.selector.refresh_steps))
        # selector.refresh_data=all: refreshes also fit on the online transitions (the ensemble sees what the
        # hybrid policy's actions led to in the states the agent visits, crashes under physics' actions included)
        self._ensemble_sees_online = (self.ensemble is not None and int(cfg.selector.refresh_every) > 0
                                      and str(cfg.selector.refresh_data) == "all")
        self.counters = Counters()
        modules = {"loss": self.loss, **({"ensemble": self.ensemble} if self.ensemble is not None else {})}
        self.objects = {"modules": modules, "optimizers": self.optimizers,
                        "replay_buffers": {"replay": self.replay, "warmup": self.warmup_buffer}}
        self.transform = builders.find_transform(self.env, InterventionTransform) if self.env is not None else None
        self.pacing = builders.find_transform(self.env, RealtimePacing) if self.env is not None else None
        periodic = checkpoint_dir is not None and int(cfg.checkpoint.every_frames) > 0
        self.journal = BatchJournal(Path(checkpoint_dir) / "journal") if periodic else None
        self.pending = None  # the single backend's episodes ended inside the batch being collected
        if self.journal is not None and self.env is not None:
            self.pending = PendingEpisodesJournal(self.journal, int(cfg.collector.frames_per_batch), self._actor_state)
            self.env.append_transform(self.pending)  # last: it copies each step as the collector stores it
        self.updater = builders.build_updater(cfg, self.loss, self.optimizers, soft_update, self.replay, self.actor,
                                              update_threads, self.device)
        self.collector, self.losses, self.saved_step, self.disconnects = None, {}, -1, 0
        self.resumed_collection: tuple[dict, dict | None] | None = None  # (collection, mentor state) to continue

    @property
    def done(self) -> bool:
        return self.counters.frames >= int(self.cfg.collector.total_frames)

    @property
    def cpu_actor(self):
        """The actor to evaluate on the CPU: the learner's own, or with ``optim.device`` its synced CPU copy."""
        return self.actor if self.device is None else self.updater.acting_actor

    def run_info(self) -> dict:
        """What a checkpoint must match to be resumed (checked by :func:`check_resumable`)."""
        from pe_rlhf import __version__

        return {"pe_rlhf_version": __version__, "env_config": self.env_config.to_dict()}

    def resume(self) -> tuple[list[JournalEntry], JournalEntry | None]:
        """Load the newest checkpoint; return the journal entries written after it, and the pending
        file that continues them (None if there is none)."""
        from pe_rlhf.runtime.checkpoint import find_checkpoint, load_checkpoint

        state = load_checkpoint(self.checkpoint_dir, **self.objects)
        check_resumable(state.get("run"), self.run_info(), find_checkpoint(self.checkpoint_dir))
        self.saved_step = int(state["step"])
        self.logger.truncate_after(self.saved_step + 1)  # rows after the checkpoint are logged again
        self.counters.load_state_dict(state["counters"])
        self.schedule.load_state_dict(state["schedule"])
        self.restore_actors(state)
        if state.get("collection") is not None:  # the episode in progress at the checkpoint (single backend)
            self.resumed_collection = (state["collection"], state["mentor"])
        if self.journal is None:
            return [], None
        entries = self.journal.entries_after(self.saved_step)
        pending = self.journal.pending_at(entries[-1].end if entries else self.saved_step)
        if entries or pending is not None:  # collection went on after the checkpoint: its episode is not the next
            self.resumed_collection = None
        return entries, pending

    def restore_actors(self, state: dict) -> None:
        """The transform's step count and the mentor's state (multi-worker backends restart theirs)."""
        if self.transform is not None:
            self.transform.total_steps = int(state["transform_steps"])
            if state["mentor"] is not None:
                self.mentor.load_state_dict(state["mentor"])

    def _actor_state(self) -> dict:
        return {"transform_steps": int(self.counters.frames) if self.transform is None else self.transform.total_steps,
                "mentor": self.mentor.state_dict() if self.mentor is not None else None}

    def start(self) -> None:
        cfg, c = self.cfg, self.counters
        self.updates0, self.update_seconds0 = c.updates, c.update_seconds
        self.started = time.time()
        self.next_eval = next_multiple(c.frames, int(cfg.eval.every_frames))
        self.next_ckpt = next_multiple(c.frames, int(cfg.checkpoint.every_frames))
        self.bar = tqdm(total=int(cfg.collector.total_frames), initial=int(c.frames), desc=method_name(cfg),
                        unit="step")
        self.updater.start()  # optim.async_updates: the learner thread (pe_rlhf.training.background_updates)

    def collect(self) -> None:
        remaining = int(self.cfg.collector.total_frames) - int(self.counters.frames)
        if remaining <= 0:
            return
        if self.pending is not None:
            self.pending.restart(int(self.counters.frames))
        rng = capture_rng() if self.resumed_collection is not None else None
        self.collector = builders.build_collector(self.cfg, self.env, self.updater.policy, remaining,
                                                  ensemble=self.ensemble, start_frames=int(self.counters.frames))
        if self.resumed_collection is not None:  # continue the checkpoint's episode, not the collector's reset
            restore_collection(self.collector, self.transform, *self.resumed_collection)
            restore_rng(rng)  # as if no collector had been built here (the original's went on stepping)
            self.resumed_collection = None
        t_env = time.time()
        for batch in self.collector:
            self.counters.env_seconds += time.time() - t_env
            if self.done:
                break
            self.process(batch)
            t_env = time.time()

    def process(self, batch, journaled: bool = False) -> None:
        """One iteration on a batch: journal, buffers, ensemble fit, updates, log, eval, checkpoint."""
        cfg, c = self.cfg, self.counters
        if self.journal is not None and not journaled:  # on disk before anything else happens to it
            self.journal.write(batch, int(c.frames), self._actor_state())
            self.journal.discard_pending(int(c.frames))  # its pending files: the whole batch is in now
        warmup = c.frames < int(cfg.collector.warmup_steps)
        m = batch_metrics(batch)
        c.add(m, warmup)
        if warmup or self._ensemble_sees_online:  # online: the executed (hybrid) action and its env reward
            self.warmup_buffer.extend(ensemble_transitions(batch).reshape(-1))  # (N, T) with multisync: time last
        if warmup:
            batch = relabel_warmup(batch, keep_agent_action=bool(cfg.collector.warmup_gap))
            m["intervention_cost"] = 0.0  # forced mentor driving is no takeover: nothing is charged
        with self.updater.lock:  # the learner thread samples from it
            self.replay.extend(batch.reshape(-1))
        self._fit_ensemble()
        backlog = self.updater.backlog  # updates owed by earlier batches, not run yet: 0 while the learner keeps up
        if c.frames >= int(cfg.collector.learning_starts):
            self.updater.notify_frames(int(m["steps"]))  # sync: the updates these frames pay for run here
            self.losses = self.updater.latest_losses() or self.losses
            if self.collector is not None:
                builders.sync_policy(self.collector)
        c.updates = self.updates0 + self.updater.updates_done
        c.update_seconds = self.update_seconds0 + self.updater.update_seconds
        metrics = iteration_log(c, m, self.losses, self.started)
        metrics["time/update_threads"] = float(self.updater.threads)
        metrics["train/update_backlog"] = float(backlog)
        metrics.update(pacing_log(self.pacing, int(m["steps"])))
        disconnects = int(getattr(self.mentor, "disconnects", 0) or 0)  # a person's window closed, pad unplugged
        metrics["train/mentor_disconnects"] = float(disconnects)
        fatigue = getattr(self.mentor, "fatigue", None)  # a simulated mentor's noise/error multiplier
        if isinstance(fatigue, (int, float)):
            metrics["train/mentor_fatigue"] = float(fatigue)
        if c.frames >= self.next_eval:
            self.next_eval = next_multiple(c.frames, int(cfg.eval.every_frames))
            with self.updater.paused():
                summary = evaluate_actor(self.cpu_actor, cfg, self.env_config, int(cfg.eval.episodes))
            for k in EVAL_KEYS:
                metrics[f"eval/{k}_mean"], metrics[f"eval/{k}_std"] = summary[k]["mean"], summary[k]["std"]
        self.logger.log(int(c.frames), metrics)
        self.bar.update(int(m["steps"]))
        self.bar.set_postfix(takeover=f"{metrics['train/takeover_rate']:.2f}", violations=int(c.safety_violations),
                             succ=f"{metrics['train/success_rate_total']:.2f}")
        if self.checkpoint_dir is not None and (c.frames >= self.next_ckpt or disconnects > self.disconnects):
            self.next_ckpt = next_multiple(c.frames, int(cfg.checkpoint.every_frames))
            with self.updater.paused():  # networks, optimisers and counters from one moment
                self.save()
        self.disconnects = disconnects

    def _fit_ensemble(self) -> None:
        cfg = self.cfg
        fit_steps = self.schedule.due(int(self.counters.frames)) if self.ensemble is not None else 0
        if not fit_steps:
            return
        fit_q_ensemble(self.ensemble, self.warmup_buffer, steps=fit_steps, batch_size=int(cfg.selector.batch_size),
                       gamma=float(cfg.loss.gamma), lr=float(cfg.selector.lr),
                       target_noise=float(cfg.selector.target_noise), tau=float(cfg.selector.tau),
                       loss=str(cfg.selector.fit_loss), seed=int(cfg.seed))
        self.ensemble.requires_grad_(False)
        if self.collector is not None:
            builders.push_ensemble_weights(self.collector, self.ensemble)

    def save(self) -> Path:
        """A checkpoint of everything at the current frame count (call with the learner paused or stopped);
        journal files it makes redundant are deleted."""
        from pe_rlhf.runtime.checkpoint import save_checkpoint

        c = self.counters
        c.updates = self.updates0 + self.updater.updates_done
        state = {"counters": c.state_dict(), "schedule": self.schedule.state_dict(), **self._actor_state(),
                 "collection": capture_collection(self.collector, self.transform), "run": self.run_info()}
        path = save_checkpoint(self.checkpoint_dir, step=int(c.frames), keep=int(self.cfg.checkpoint.keep),
                               **self.objects, state=state)
        self.saved_step = int(c.frames)
        if self.journal is not None:
            self.journal.prune(self.saved_step)
        return path

    def stop_on_error(self, error: FloatingPointError) -> FloatingPointError:
        """Stop the learner, checkpoint what was collected (the updates stopped before the bad step),
        and return the error to raise, saying where the checkpoint is."""
        with contextlib.suppress(BaseException):  # the learner thread died of ``error`` already
            self.updater.stop(finish=False)
        self.bar.close()
        if self.checkpoint_dir is None:
            return FloatingPointError(f"{error} (no checkpoint directory: nothing saved)")
        path = self.save()
        return FloatingPointError(f"{error}. Saved checkpoint {path} (frame {int(self.counters.frames)}, every "
                                  "collected transition included); fix the cause (e.g. a lower optim.lr) and --resume")

    def shutdown_collector(self) -> None:
        if self.collector is not None:
            builders.shutdown_collector(self.collector)
            self.collector = None

    def finish(self, out_dir: Path) -> dict:
        """Owed updates, a last checkpoint, the final evaluation, ``actor.pt`` (and the GIF)."""
        c = self.counters
        self.updater.stop()  # async: the updates still owed run first, so the run keeps its update-to-data ratio
        c.updates = self.updates0 + self.updater.updates_done
        c.update_seconds = self.update_seconds0 + self.updater.update_seconds
        self.bar.close()
        if self.checkpoint_dir is not None and c.frames > self.saved_step:
            self.save()
        final = evaluate_actor(self.cpu_actor, self.cfg, self.env_config, int(self.cfg.eval.episodes))
        final["algorithm"] = algorithm_name(self.cfg)
        final["training"] = c.state_dict()
        torch.save({k: v.detach().cpu() for k, v in self.actor.state_dict().items()}, out_dir / "actor.pt")
        if self.cfg.eval.video:
            final["video"] = record_test_video(self.cpu_actor, self.cfg, self.env_config, out_dir / VIDEO_NAME,
                                               self.logger, int(c.frames))
        return final


def check_resumable(saved: dict | None, current: dict, checkpoint) -> None:
    """Refuse a checkpoint trained under another env config (ValueError naming each field); warn when
    another pe_rlhf version wrote it (the checkpoint format, checked on loading, is what must agree).
    Checkpoints from before this record (``saved`` None) are taken as they are."""
    if saved is None:
        return
    if saved.get("pe_rlhf_version") != current["pe_rlhf_version"]:
        warnings.warn(f"{checkpoint} was written by pe_rlhf {saved.get('pe_rlhf_version')}, this is "
                      f"{current['pe_rlhf_version']} (same checkpoint format: resuming)", stacklevel=3)
    env, now = saved.get("env_config") or {}, current["env_config"]
    bad = [f"env.{k}: checkpoint {env.get(k)!r}, now {v!r}" for k, v in now.items() if k in env and env[k] != v]
    if bad:
        raise ValueError(f"cannot resume from {checkpoint}: it was trained under another env config ("
                         + "; ".join(bad) + "); resume with the run's own config.yaml values")
