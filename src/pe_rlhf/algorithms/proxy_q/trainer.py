"""The PE-RLHF (HACO, HAIM-DRL, PVP) learner's objects and helpers: warm-up, value-source fit, online collection with
takeovers, updates.

``recipes/pe_rlhf/train.py`` owns the loop: for each of :meth:`ProxyQLearner.batches` it calls
:meth:`ProxyQLearner.store`, the updater's ``notify_frames`` (the updates), :meth:`ProxyQLearner.row` and
:meth:`pe_rlhf.runtime.run.Run.after_batch` (the cadence every method shares: evaluations, checkpoints, the
log). The batches, in phases:

1. warm-up: the mentor (or, with ``collector.warmup_policy``, the trained actor of an earlier run: the
   expert-policy warm-up) drives ``collector.warmup_steps`` steps (the transform forces it); the
   transitions, with the env reward, fill a warm-up buffer and, relabelled
   (:func:`~pe_rlhf.algorithms.proxy_q.steps.relabel_warmup`), the replay buffer;
2. the Q-ensemble is fitted on the warm-up data, then frozen (the paper);
3. online: the collector runs the actor inside ``InterventionTransform`` (mentor + physics +
   selector); ``optim.updates_per_batch`` PERLHFLoss updates follow every batch once
   the first batch is in (with ``optim.async_updates``, at the same ratio in a
   learner thread beside acting: :mod:`pe_rlhf.algorithms.proxy_q.background_updates`; ``collector.realtime_hz``
   holds the env to a steady step rate for a person: :class:`~pe_rlhf.transforms.RealtimePacing`);
4. (the run's) every ``eval.every_frames``: evaluation on the test split without the mentor; every
   ``checkpoint.every_frames``: a checkpoint (``--resume DIR`` continues from it).

What a run survives: each collected batch is journaled (:mod:`pe_rlhf.runtime.journal`) before
it is used, and with the ``single`` backend each episode that ends inside the batch being collected
is written at once (:mod:`pe_rlhf.runtime.episode_journal`), so ``--resume`` after a kill replays
the batches since the checkpoint with the RNG states they arrived with, then completes the
collected batch's steps up to its last finished episode with steps from a fresh episode (its rows and
updates land on the frames an uninterrupted run's do), and loses only the steps of the episode in
progress since the batch began (multi-worker backends: the batch being collected);
a non-finite loss, gradient or parameter stops updates with a ``FloatingPointError`` naming it,
after a checkpoint of everything collected; a mentor's disconnect (a person's window closed,
gamepad unplugged: ``disconnects``) triggers a checkpoint at the end of that batch; the run ends
with a checkpoint of its last frame; ``train/sim_errors_total`` counts episodes the simulator's
faults ended (:mod:`pe_rlhf.envs.driving_env`).

A checkpoint taken while collecting (``single`` backend) holds the collection in progress
(:mod:`pe_rlhf.runtime.collection_state`: the episode, the takeover, the selector's veto count, the
collector's carrier), so ``--resume`` from it with no journal after it (a run's folder kept at that
checkpoint) continues bit-identically to the run that went on; after a kill, the journal's batches are
replayed and collection starts a fresh episode.

``collector.backend`` picks the collector (:func:`pe_rlhf.algorithms.proxy_q.builders.build_collector`). With
a multi-worker backend the workers own the envs, mentors and transforms, so a resume restarts the
workers' simulated mentors (fatigue, RNG) and sets their transform step counters from the
checkpointed global frame count (no repeated warm-up); everything else (networks, optimisers,
buffers, counters) resumes exactly.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from pe_rlhf.modules import EnsembleSchedule
from pe_rlhf.objectives import fit_q_ensemble
from pe_rlhf.runtime.checkpoint import capture_rng, restore_rng
from pe_rlhf.runtime.collection_state import capture_collection, restore_collection
from pe_rlhf.runtime.run import Learner
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import algorithm_name, method_name
from pe_rlhf.algorithms.proxy_q.steps import (VIDEO_NAME, Counters, batch_metrics, cut_to, ensemble_transitions,
                                              iteration_log, pacing_log, record_test_video, relabel_warmup)
from pe_rlhf.transforms import InterventionTransform, RealtimePacing

if TYPE_CHECKING:
    from pe_rlhf.runtime.journal import JournalEntry

# Settings a --resume cannot change (pe_rlhf.runtime.resume_changes): the checkpoint's state would override them, or
# the saved data was cut by them; every other change is applied (and announced).
RESUME_REFUSED = {
    "seed": "the checkpoint's RNG states continue the run's random streams",
    "profile": "a resume composes the run's config.yaml without a profile; set the fields themselves",
    "env": "the networks learned that world",
    "mentor": "the checkpoint holds that mentor's state",
    "collector.frames_per_batch": "the journal's batches and pending episodes are cut at the run's size",
    "collector.warmup_steps": "the warm-up data and the fitted ensemble are the run's",
    "collector.warmup_policy": "the warm-up data are the run's",
    "collector.backend": "the collection in progress belongs to the run's backend",
    "collector.num_workers": "the collection in progress belongs to the run's workers",
    "replay_buffer.takeover_share": "the buffers' layout (takeover rows apart or not) is the checkpoint's",
    "loss.hidden": "the checkpoint's networks have the run's sizes",
    "loss.num_qvalue_nets": "the checkpoint's networks are the run's",
    "loss.num_intervention_qvalue_nets": "the checkpoint's networks are the run's",
    "disturbance.num_qvalue_nets": "the checkpoint's networks are the run's",
    "loss.alpha_init": "the checkpoint's alpha continues",
    "loss.target_entropy": "the checkpoint's loss holds the run's target entropy",
    "selector.num_members": "the checkpoint's ensemble has the run's size",
    "physics.enabled": "the checkpoint's modules are the run's",
    "disturbance.enabled": "the checkpoint's critics are the run's",
    "actor_selection": "a run picks its actor over the whole run",
    "checkpoint.every_frames": lambda was, now: ("0 turns the journal off, and with it the batches it holds"
                                                 if int(now or 0) == 0 and int(was or 0) > 0 else None),
}


class ProxyQLearner(Learner):
    """PE-RLHF, HACO, HAIM-DRL and PVP as a :class:`~pe_rlhf.runtime.run.Learner`: its objects, and the pieces of the
    work on each batch, collected or replayed from the journal on ``--resume`` (:mod:`pe_rlhf.runtime.journal`).
    It has no ``learn``: the loop is ``recipes/pe_rlhf/train.py``'s (:meth:`store`, the updater's ``notify_frames``,
    :meth:`row`), which calls :class:`~pe_rlhf.runtime.run.Run`'s ``begin``/``after_batch``/``finish``, not
    ``Run.train``."""

    def __init__(self, cfg, logger, checkpoint_dir: Path | None, update_threads: int):
        from pe_rlhf.runtime.config import driving_config
        from pe_rlhf.runtime.episode_journal import PendingEpisodesJournal
        from pe_rlhf.runtime.journal import BatchJournal

        self.cfg, self.logger, self.name = cfg, logger, method_name(cfg)  # the logger: the test episode's video
        self.env_config = driving_config(cfg)
        self.value_source = builders.build_value_source(cfg)
        self.env, self.mentor = builders.build_local_env(cfg, self.env_config, self.value_source)  # None: workers own them
        self.learner_actor = builders.build_actor(cfg)
        self.loss, soft_update = builders.build_loss(cfg, self.learner_actor)
        self.device = builders.learner_device(cfg)  # None: the CPU, acting with the learner's actor
        if self.device is not None:
            self.loss.to(self.device)  # actor, critics, targets (the actor's parameters are the loss's)
        self.optimizers = builders.build_optimizers(cfg, self.loss)
        self.replay = builders.build_replay_buffer(cfg, balanced=True)
        self.warmup_buffer = builders.build_replay_buffer(cfg)
        # an expert or a forecast is never fitted
        self.schedule = EnsembleSchedule(int(cfg.collector.warmup_steps), 0, builders.ensemble_fit_steps(cfg))
        self.counters = Counters()
        # "ensemble": the checkpoint's name for the value source's module (a forecast has no parameters)
        modules = {"loss": self.loss, **({"ensemble": self.value_source} if self.value_source is not None else {})}
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
        self.updater = builders.build_updater(cfg, self.loss, self.optimizers, soft_update, self.replay,
                                              self.learner_actor, update_threads, self.device)
        self.collector, self.losses, self.disconnects, self.backlog = None, {}, 0, 0
        self.journaled: list[JournalEntry] = []  # on --resume: the killed run's batches since the checkpoint,
        self.journaled_pending: JournalEntry | None = None  # and its last batch up to the last finished episode
        self.resumed_collection: tuple[dict, dict | None] | None = None  # (collection, mentor state) to continue

    @property
    def progress(self) -> int:
        return int(self.counters.frames)

    @property
    def done(self) -> bool:
        return self.counters.frames >= int(self.cfg.collector.total_frames)

    @property
    def actor(self):
        """The actor to evaluate on the CPU: the learner's own, or with ``optim.device`` its synced CPU copy."""
        return self.learner_actor if self.device is None else self.updater.acting_actor

    def checkpoint_objects(self, checkpoint: Path | None = None) -> dict:
        return self.objects

    def state_dict(self) -> dict:
        c = self.counters
        c.updates = self.updates0 + self.updater.updates_done
        return {"counters": c.state_dict(), "schedule": self.schedule.state_dict(), **self._actor_state(),
                "collection": capture_collection(self.collector, self.transform)}

    def load_state_dict(self, state: dict) -> None:
        """The checkpoint's counters, schedule and actors; the journal entries written after it, and the
        pending file that continues them, to replay."""
        self.counters.load_state_dict(state["counters"])
        self.schedule.load_state_dict(state["schedule"])
        self.restore_actors(state)
        if state.get("collection") is not None:  # the episode in progress at the checkpoint (single backend)
            self.resumed_collection = (state["collection"], state["mentor"])
        if self.replay_journal(int(state["step"])) > int(state["step"]):  # collection went on: its episode is not
            self.resumed_collection = None  # the next

    def replay_journal(self, step: int) -> int:
        """Queue the journal's batches from frame ``step`` on, and the pending file that continues them, to be
        trained on first; returns the frame they reach (``step`` when there is nothing to replay)."""
        if self.journal is None:
            return step
        self.journaled = self.journal.entries_after(step)
        self.journaled_pending = self.journal.pending_at(self.journaled[-1].end if self.journaled else step)
        return max([step] + [e.end for e in self.journaled] + [getattr(self.journaled_pending, "end", step)])

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
        self.updates0, self.update_seconds0 = self.counters.updates, self.counters.update_seconds
        self.updater.start()  # optim.async_updates: the learner thread (pe_rlhf.algorithms.proxy_q.background_updates)

    def batches(self):
        """The killed run's journaled batches since the checkpoint (as it processed them), then collection, whose
        first batch completes the killed run's last one up to its last finished episode; ``(batch, journaled)``
        pairs."""
        try:
            for entry in self.journaled:
                if self.done:
                    return
                restore_rng(entry.rng)
                yield entry.batch, True
                self.restore_actors(entry.state)
            pending = self.journaled_pending if not self.done else None
            if pending is not None:
                restore_rng(pending.rng)
                self.restore_actors(pending.state)  # first: journaled with it, and a checkpoint after it saves it
            yield from self.collect(pending.batch if pending is not None else None)
        finally:
            if self.collector is not None:
                builders.shutdown_collector(self.collector)
                self.collector = None

    def collect(self, head=None):
        """Collected batches from the run's frame count on, the first one completing ``head`` (the killed run's
        pending steps of the batch it was collecting) and ending on the ``collector.frames_per_batch`` grid, so
        that rows and updates land where an uninterrupted run's do; the last one cut at ``collector.total_frames``."""
        total, frames = int(self.cfg.collector.total_frames), int(self.counters.frames)
        held = 0 if head is None else int(head.numel())
        whole = (frames + held) % int(self.cfg.collector.frames_per_batch) == 0  # an episode ended on its last step
        if head is not None and (whole or frames + held >= total):  # nothing to complete, or the run ends in it
            yield cut_to(head, total - frames), False
            head, held, frames = None, 0, int(self.counters.frames)
        if frames >= total:
            return
        if self.pending is not None:  # a kill now keeps ``head`` and the episodes that end after it
            self.pending.restart(frames, head)
        rng = capture_rng() if self.resumed_collection is not None else None
        policy = builders.build_collection_policy(self.cfg, self.updater.policy)
        self.collector = builders.build_collector(self.cfg, self.env, policy, total - frames - held,
                                                  value_source=self.value_source, start_frames=frames + held)
        if self.resumed_collection is not None:  # continue the checkpoint's episode, not the collector's reset
            restore_collection(self.collector, self.transform, *self.resumed_collection)
            restore_rng(rng)  # as if no collector had been built here (the original's went on stepping)
            self.resumed_collection = None
        t_env = time.time()
        for batch in builders.batches_on_grid(self.collector, frames + held):
            self.counters.env_seconds += time.time() - t_env
            if self.done:
                break
            if head is not None:
                batch, head = torch.cat([head, batch.rename(None)]), None
            yield cut_to(batch, int(self.cfg.collector.total_frames) - int(self.counters.frames)), False
            t_env = time.time()

    def store(self, item) -> dict[str, float]:
        """A batch from :meth:`batches` (``(batch, journaled)``) into the run: journaled first (on disk before
        anything else happens to it), counted, the warm-up's relabelled (and kept to fit the value source on), the
        replay buffer extended, the value source fitted when due. Returns the batch's counts
        (:func:`~pe_rlhf.algorithms.proxy_q.steps.batch_metrics`)."""
        batch, journaled = item
        cfg, c = self.cfg, self.counters
        if self.journal is not None and not journaled:
            self.journal.write(batch, int(c.frames), self._actor_state())
            self.journal.discard_pending(int(c.frames))  # its pending files: the whole batch is in now
        warmup = c.frames < int(cfg.collector.warmup_steps)
        m = batch_metrics(batch)
        c.add(m, warmup)
        if warmup:
            self.warmup_buffer.extend(ensemble_transitions(batch).reshape(-1))  # (N, T) with multisync: time last
            batch = relabel_warmup(batch)
            m["intervention_cost"] = 0.0  # forced mentor driving is no takeover: nothing is charged
        with self.updater.lock:  # the learner thread samples from it
            self.replay.extend(batch.reshape(-1))
        self._fit_value_source()
        self.backlog = self.updater.backlog  # updates owed by earlier batches, not run yet: 0 while it keeps up
        return m

    @property
    def learning(self) -> bool:
        """Whether updates run: from the first batch on (``collector.frames_per_batch`` frames are in)."""
        return self.counters.frames >= int(self.cfg.collector.frames_per_batch)

    def row(self, m: dict[str, float]) -> dict[str, float]:
        """After the batch's updates: the latest losses, the collector's policy weights synced, the batch's row of
        metrics (``m``: :meth:`store`'s counts); a mentor's disconnect asks for a checkpoint."""
        c = self.counters
        if self.learning:
            self.losses = self.updater.latest_losses() or self.losses
            if self.collector is not None:
                builders.sync_policy(self.collector)
        c.updates = self.updates0 + self.updater.updates_done
        c.update_seconds = self.update_seconds0 + self.updater.update_seconds
        metrics = iteration_log(c, m, self.losses)
        metrics["time/update_threads"] = float(self.updater.threads)
        metrics["train/update_backlog"] = float(self.backlog)
        metrics.update(pacing_log(self.pacing, int(m["steps"])))
        disconnects = int(getattr(self.mentor, "disconnects", 0) or 0)  # a person's window closed, pad unplugged
        metrics["train/mentor_disconnects"] = float(disconnects)
        fatigue = getattr(self.mentor, "fatigue", None)  # a simulated mentor's noise/error multiplier
        if isinstance(fatigue, (int, float)):
            metrics["train/mentor_fatigue"] = float(fatigue)
        self.checkpoint_requested, self.disconnects = disconnects > self.disconnects, disconnects
        return metrics

    def postfix(self, row: dict[str, float]) -> dict:
        return {"takeover": f"{row['train/takeover_rate']:.2f}", "violations": int(self.counters.safety_violations),
                "succ": f"{row['train/success_rate_total']:.2f}"}

    def _fit_value_source(self) -> None:
        cfg = self.cfg
        fit_steps = self.schedule.due(int(self.counters.frames)) if self.value_source is not None else 0
        if not fit_steps:
            return
        fit = builders.ENSEMBLE_FIT
        fit_q_ensemble(self.value_source, self.warmup_buffer, steps=fit_steps, batch_size=fit["batch_size"],
                       gamma=float(cfg.loss.gamma), lr=fit["lr"], target_noise=fit["target_noise"], tau=fit["tau"],
                       seed=int(cfg.seed))
        self.value_source.requires_grad_(False)
        if self.collector is not None:
            builders.push_value_source_weights(self.collector, self.value_source)

    def paused(self):
        return self.updater.paused()

    def saved(self, step: int) -> None:
        if self.journal is not None:  # its files up to the checkpoint are redundant now
            self.journal.prune(step)

    def stop(self, finish: bool = True) -> None:
        """Join the learner thread: after the updates still owed (``finish``: the run keeps its update-to-data
        ratio) or after the one in flight."""
        self.updater.stop(finish=finish)
        if finish:
            self.counters.updates = self.updates0 + self.updater.updates_done
            self.counters.update_seconds = self.update_seconds0 + self.updater.update_seconds

    def summary(self, out_dir: Path) -> dict:
        summary = {"algorithm": algorithm_name(self.cfg), "training": self.counters.state_dict()}
        if self.cfg.eval.video:
            summary["video"] = record_test_video(self.actor, self.cfg, self.env_config, out_dir / VIDEO_NAME,
                                                 self.logger, int(self.counters.frames))
        return summary
