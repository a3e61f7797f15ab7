"""One training run of any method: a :class:`Learner`'s batches in one loop, with the cadence, ``--resume`` and
finish that every recipe shares.

:meth:`Run.train`, top to bottom:

1. with ``resume``, the newest checkpoint (:mod:`pe_rlhf.runtime.checkpoint`) is loaded into the learner's
   modules, optimisers and replay buffers, its env config checked (:func:`check_resumable`) and the rows
   ``metrics.csv`` holds after it dropped (they are logged again); with no complete checkpoint yet (a run killed
   before its first), the fresh learner replays its journal from frame 0 (:meth:`Learner.replay_journal`);
2. a fresh run's ``pretrain`` row at step 0, when the learner has one (HG-DAgger, IWR: BC on demonstrations);
3. each batch the learner yields (frames collected online, or a round of offline updates) goes to its
   ``learn``, which returns the row; every ``eval_every`` units of progress a deterministic evaluation on
   ``eval.split`` adds the ``eval/*`` columns; the row is logged every ``logger.log_every`` batches (and
   with an evaluation, and the last); every ``checkpoint_every`` (or when the learner asks) a checkpoint;
4. a non-finite loss, gradient or parameter (``FloatingPointError``): a checkpoint of what there is, and the
   error, saying where it is;
5. the finish: a last checkpoint, the final evaluation with the learner's ``summary``, ``actor.safetensors``.

With ``actor_selection.every_frames`` (a config group; 0 or absent: off) the actor is also scored every that many
units on train scenes, and the best snapshot, not the last, becomes the run's actor
(:mod:`pe_rlhf.runtime.actor_selection`).
"""

from __future__ import annotations

import contextlib
import time
import warnings
from pathlib import Path

import torch
from tqdm import tqdm

from pe_rlhf import durable
from pe_rlhf.evaluation import TorchRLPolicyAdapter, evaluate
from pe_rlhf.runtime.actor_selection import SELECTED_MODULE, ActorSelection
from pe_rlhf.runtime.buffer_rows import drop_non_finite_rows
from pe_rlhf.runtime.checkpoint import (CheckpointError, CheckpointMismatch, find_checkpoint, list_checkpoints,
                                        load_checkpoint, save_checkpoint)
from pe_rlhf.runtime.resume_changes import optimizer_settings, restore_optimizer_settings
from pe_rlhf.threads import torch_threads

ACTOR_FILE = "actor.safetensors"  # weights only; runs from before it have actor.pt (still loaded)
EVAL_KEYS = ("episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
             "overtake_count")


class Learner:
    """What a method plugs into :class:`Run`; the hooks defined here are optional.

    A learner has ``name`` (the progress bar's label), ``env_config`` (its :class:`~pe_rlhf.envs.DrivingConfig`),
    ``actor`` (evaluated deterministically, saved as ``actor.safetensors``), ``progress`` (frames, or updates offline: the
    step of rows and checkpoints), and ``batches()`` (the work, one item per ``learn``; it stops when the run is
    complete), ``learn(batch)`` (returns the batch's row of metrics; only :meth:`Run.train` calls it, a recipe that
    owns its loop calls its learner's own pieces), ``checkpoint_objects(checkpoint=None)``
    (``modules``, ``optimizers`` and ``replay_buffers`` to save, or to load ``checkpoint`` into),
    ``load_state_dict(state)`` (``state["step"]`` is its progress) and ``summary(out_dir)`` (what
    ``final_eval.json`` adds to the final evaluation: ``algorithm``, ``training`` totals, ...). With ``timers``
    (the names of waiting for a batch and of learning) the run times both, and its evaluations, as
    ``time/<name>_seconds`` across the run's sessions.
    """

    unit, timers = "frame", ()
    checkpoint_requested = False  # set by ``learn``: a checkpoint after this batch, whatever the cadence

    def state_dict(self) -> dict:
        return {}

    def pretrain(self) -> dict[str, float] | None:
        """A fresh run's row at step 0, or None."""
        return None

    def start(self) -> None:
        """Before the first batch of this session."""

    def paused(self):
        """Around periodic evaluations and checkpoints: no update runs inside (a learner thread's)."""
        return contextlib.nullcontext()

    def stop(self, finish: bool = True) -> None:
        """Before the finish (``finish``: run the updates still owed) or after an error."""

    def saved(self, step: int) -> None:
        """After each checkpoint, at ``step``."""

    def replay_journal(self, step: int) -> int:
        """Queue what the learner journaled from ``step`` on to be learned first; returns the progress it reaches
        (``step``: nothing journaled, the default)."""
        return step

    def postfix(self, row: dict[str, float]) -> dict:
        """The progress bar's postfix."""
        return {}


class Run:
    """Drives a :class:`Learner` to ``total`` units of progress (module docstring), with ``cfg.eval``,
    ``cfg.checkpoint.keep`` and ``cfg.logger.log_every``; ``logger`` has ``log(step, metrics)`` and
    ``truncate_after``. No ``checkpoint_dir``: nothing is saved."""

    def __init__(self, cfg, learner: Learner, logger, checkpoint_dir: Path | None, *, total: int, eval_every: int,
                 checkpoint_every: int):
        self.cfg, self.learner, self.logger, self.checkpoint_dir = cfg, learner, logger, checkpoint_dir
        self.total, self.eval_every, self.checkpoint_every = int(total), int(eval_every), int(checkpoint_every)
        self.iterations, self.saved_step, self.started = 0, -1, time.time()
        self.seconds = dict.fromkeys((*learner.timers, "eval", "earlier_sessions"), 0.0) if learner.timers else {}
        picking = getattr(cfg, "actor_selection", None)  # absent (the baselines' configs): off
        self.selection = None
        if picking is not None and int(picking.every_frames) > 0:
            self.selection = ActorSelection(learner.actor, int(picking.every_frames), int(picking.episodes))

    @property
    def progress(self) -> int:
        return int(self.learner.progress)

    @property
    def done(self) -> bool:
        return self.progress >= self.total

    def wall_time(self) -> float:
        return self.seconds.get("earlier_sessions", 0.0) + time.time() - self.started

    def timed(self, timer: int | str, since: float) -> None:
        """Add the seconds since ``since`` to a timer (an index into the learner's ``timers``, or ``"eval"``)."""
        if self.seconds:
            self.seconds[self.learner.timers[timer] if isinstance(timer, int) else timer] += time.time() - since

    def run_info(self) -> dict:
        """What a checkpoint must match to be resumed (checked by :func:`check_resumable`)."""
        from pe_rlhf import __version__

        return {"pe_rlhf_version": __version__, "env_config": self.learner.env_config.to_dict()}

    def train(self, out_dir: Path, resume: bool = False) -> dict:
        """The whole run (module docstring): :meth:`begin`, the learner's ``learn`` on each of its batches followed by
        :meth:`after_batch`, :meth:`finish`; returns the final evaluation summary dict. (A recipe that owns its loop,
        as ``recipes/pe_rlhf/train.py``, calls the same pieces.)"""
        self.begin(out_dir, resume)
        batches = self.learner.batches()
        with self.batches_closed(batches):
            t = time.time()
            for batch in batches:
                self.timed(0, t)
                before, t = self.progress, time.time()
                row = self.learner.learn(batch)
                self.timed(1, t)
                self.after_batch(row, before)
                t = time.time()
        return self.finish(Path(out_dir))

    def begin(self, out_dir: Path, resume: bool = False) -> None:
        """Before the first batch: with ``resume`` the newest intact checkpoint (or the journal) loaded, a fresh
        run's ``pretrain`` row, the cadence from the current progress, the progress bar, the learner started."""
        if resume:
            self.resume(out_dir)
        if self.progress == 0:
            t = time.time()
            row = self.learner.pretrain()
            if row is not None:
                self.timed(1, t)
                self.logger.log(0, {**row, "wall_time": self.wall_time()})
        self.next_eval = next_multiple(self.progress, self.eval_every)
        self.next_pick = next_multiple(self.progress, self.selection.every if self.selection else 0)
        self.next_ckpt = next_multiple(self.progress, self.checkpoint_every)
        self.bar = tqdm(total=self.total, initial=self.progress, desc=self.learner.name, unit=self.learner.unit)
        self.learner.start()

    @contextlib.contextmanager
    def batches_closed(self, batches):
        """Around the loop over ``batches``: a non-finite loss, gradient or parameter (``FloatingPointError``)
        checkpoints what there is and stops with a message saying where it is; the batches (a collector inside)
        and the progress bar are closed whatever happens."""
        try:
            yield
        except FloatingPointError as e:
            raise self.stop_on_error(e) from e
        finally:
            batches.close()
            self.bar.close()

    def after_batch(self, row: dict[str, float], before: int) -> None:
        """After a batch's learning (its ``row``; ``before``: the progress before it): evaluate, pick and
        checkpoint when due, log."""
        self.iterations += 1
        evaluated = self.progress >= self.next_eval
        if evaluated:
            self.next_eval = next_multiple(self.progress, self.eval_every)
            with self.learner.paused():
                summary = self.evaluate()
            row.update({f"eval/{k}_{s}": summary[k][s] for k in EVAL_KEYS for s in ("mean", "std")})
        picked = self.selection is not None and self.progress >= self.next_pick
        if picked:
            self.next_pick = next_multiple(self.progress, self.selection.every)
            with self.learner.paused():
                self.score_actor()
            row.update(self.selection.row())
        row["wall_time"] = self.wall_time()
        row.update({f"time/{k}_seconds": v for k, v in self.seconds.items() if k != "earlier_sessions"})
        if self.done or evaluated or picked or self.iterations % int(self.cfg.logger.log_every) == 0:
            self.logger.log(self.progress, row)
        self.bar.update(self.progress - before)
        self.bar.set_postfix(self.learner.postfix(row), refresh=False)
        if self.checkpoint_dir is not None and (self.progress >= self.next_ckpt or self.learner.checkpoint_requested):
            self.next_ckpt = next_multiple(self.progress, self.checkpoint_every)
            with self.learner.paused():  # networks, optimisers and counters from one moment
                self.save()

    def evaluate(self, actor=None, split: str | None = None, episodes: int | None = None) -> dict:
        """A deterministic evaluation of ``actor`` (the learner's) on ``eval.split`` and ``eval.episodes``
        unless given."""
        actor = self.learner.actor if actor is None else actor
        episodes = int(self.cfg.eval.episodes if episodes is None else episodes)
        t = time.time()
        with torch_threads(1):
            summary = evaluate_actor(actor, self.cfg, self.learner.env_config, episodes, split)
        self.timed("eval", t)
        return summary

    def score_actor(self) -> None:
        """Score the learner's actor on the selection's train scenes, keeping it if it is the best so far."""
        summary = self.evaluate(split=self.selection.split, episodes=self.selection.episodes)
        self.selection.consider(self.learner.actor, self.progress, summary)

    def checkpoint_objects(self, checkpoint=None) -> dict:
        """The learner's objects, with the picked actor's copy among the modules when the run picks one."""
        objects = self.learner.checkpoint_objects(checkpoint)
        if self.selection is None:
            return objects
        return {**objects, "modules": {**objects["modules"], SELECTED_MODULE: self.selection.actor}}

    def save(self) -> Path:
        """A checkpoint of the learner and the run at the current progress (the learner paused or stopped)."""
        state = {**self.learner.state_dict(), "iterations": self.iterations, "run": self.run_info()}
        if self.selection is not None:
            state["actor_selection"] = self.selection.state_dict()
        if self.seconds:
            state["seconds"] = dict(self.seconds, earlier_sessions=self.wall_time())
        path = save_checkpoint(self.checkpoint_dir, step=self.progress, keep=int(self.cfg.checkpoint.keep),
                               **self.checkpoint_objects(), state=state)
        self.saved_step = self.progress
        self.learner.saved(self.saved_step)
        return path

    def resume(self, out_dir: Path) -> None:
        """Load the newest checkpoint into the learner and the run."""
        checkpoint = find_checkpoint(self.checkpoint_dir)
        if checkpoint is None:
            self.resume_from_start(out_dir)
            return
        objects = self.checkpoint_objects(checkpoint)
        configured = optimizer_settings(objects.get("optimizers", {}))  # this run's config, not the checkpoint's
        checkpoint, state = self.load_intact(checkpoint, objects, out_dir)
        check_resumable(state.get("run"), self.run_info(), checkpoint)
        restore_optimizer_settings(objects.get("optimizers", {}), configured)  # optim.lr on --resume: applied
        for name, buffer in self.checkpoint_objects().get("replay_buffers", {}).items():
            dropped = drop_non_finite_rows(buffer)  # such a row would stop every update again
            if dropped:
                print(f"{out_dir}: dropped {dropped} row(s) holding NaN or inf from replay buffer {name!r}", flush=True)
        if self.selection is not None:
            self.selection.load_state_dict(state["actor_selection"])
        self.saved_step, self.iterations = int(state["step"]), int(state.get("iterations", 0))
        if self.seconds and "seconds" in state:
            self.seconds = {k: float(v) for k, v in state["seconds"].items()}
        self.logger.truncate_after(self.saved_step + 1)  # rows after the checkpoint are logged again
        self.learner.load_state_dict(state)
        if self.done:  # otherwise the re-evaluation looks like training that did nothing
            print(f"{out_dir}: the run was already complete ({self.progress} of {self.total} {self.learner.unit}s); "
                  "evaluating it again (final_eval.json, the actor and the plots are rewritten)", flush=True)

    def load_intact(self, checkpoint: Path, objects: dict, out_dir: Path) -> tuple[Path, dict]:
        """Load ``checkpoint`` into ``objects``; when it is damaged (truncated, corrupt), the newest intact earlier
        one, saying so. Returns the checkpoint loaded and its state."""
        candidates = [checkpoint, *(p for p in reversed(list_checkpoints(checkpoint.parent)) if p.name < checkpoint.name)]
        for candidate in candidates:
            try:
                state = load_checkpoint(candidate, **objects)
            except CheckpointError as e:
                if candidate == candidates[-1]:
                    raise
                print(f"{out_dir}: {e}; trying the checkpoint before it", flush=True)
                continue
            except CheckpointMismatch as e:
                if SELECTED_MODULE not in e.missing + e.extra:
                    raise
                was, now = ("off", "on") if self.selection is not None else ("on", "off")
                raise ValueError(f"cannot resume from {candidate}: it was written with actor_selection {was}, this "
                                 f"run has it {now}; a run picks its actor over the whole run, so resume with the "
                                 "run's own actor_selection.every_frames (its config.yaml value)") from None
            if candidate != checkpoint:
                print(f"{out_dir}: resuming from the intact {candidate.name}; what came after it is collected again",
                      flush=True)
            return candidate, state
        raise AssertionError("unreachable")

    def resume_from_start(self, out_dir: Path) -> None:
        """No checkpoint is complete yet (killed before the first): the fresh learner (same seed, same
        initial weights) replays what its journal holds from frame 0; with nothing journaled the run starts over."""
        reached = self.learner.replay_journal(0)
        self.logger.truncate_after(0)  # every row is logged again
        what = (f"replaying the journal's {reached} {self.learner.unit}s from the start" if reached
                else "nothing was journaled either: the run starts over")
        print(f"{out_dir}: no complete checkpoint yet; {what}", flush=True)

    def stop_on_error(self, error: FloatingPointError) -> FloatingPointError:
        """Stop the learner, checkpoint what there is, and return the error to raise, saying where it is."""
        with contextlib.suppress(BaseException):  # a learner thread died of ``error`` already
            self.learner.stop(finish=False)
        if self.checkpoint_dir is None:
            return FloatingPointError(f"{error} (no checkpoint directory: nothing saved)")
        path = self.save()
        return FloatingPointError(f"{error}. Saved checkpoint {path} ({self.learner.unit} {self.progress}, everything "
                                  f"collected included). `--resume {self.checkpoint_dir.parent}` drops the replay rows holding NaN "
                                  "or inf (bad data); if the loss diverged on finite data, resume with a lower learning "
                                  f"rate, e.g. `--resume {self.checkpoint_dir.parent} optim.lr=<lower>` (a resume applies it)")

    def finish(self, out_dir: Path) -> dict:
        """The learner stopped, a last checkpoint, the final evaluation with the learner's summary, the actor."""
        self.learner.stop()
        if self.checkpoint_dir is not None and self.progress > self.saved_step:
            self.save()
        actor = self.learner.actor
        final = last = self.evaluate()
        if self.selection is not None:  # the last actor's evaluation stays beside the picked one's
            if self.progress not in self.selection.scores:
                self.score_actor()
            if self.selection.step != self.progress:
                actor = self.selection.actor
                final = self.evaluate(actor)
            final["last_actor"] = {k: v for k, v in last.items() if k != "env_config"}  # scene by scene too
            final["actor_selection"] = self.selection.summary()
        final.update(self.learner.summary(out_dir))
        if self.seconds:
            final["training"].update(wall_time_s=self.wall_time(), **{f"{k}_s": v for k, v in self.seconds.items()})
        save_weights(actor, out_dir / ACTOR_FILE)
        return final


def save_weights(module: torch.nn.Module, path: Path) -> Path:
    """``module``'s state dict as safetensors at ``path``, atomically: a temp file renamed over it, so a reader sees
    the old file or the new one, and a symlink at ``path`` is replaced, never written through."""
    return durable.save_tensors(path, module.state_dict())


def next_multiple(progress: float, every: int) -> float:
    """The next progress at which a periodic job runs (never, when ``every`` is 0)."""
    return float("inf") if every <= 0 else (int(progress) // every + 1) * every


def evaluate_actor(actor, cfg, env_config, episodes: int, split: str | None = None) -> dict:
    """Deterministic evaluation of the actor on the first ``episodes`` seeds of ``split`` (``eval.split``)."""
    from pe_rlhf.envs import scene_seeds

    seeds = scene_seeds(str(cfg.eval.split if split is None else split))[:episodes]
    return evaluate(TorchRLPolicyAdapter(actor), seeds, env_config, progress=False).to_dict()


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
