"""The learner: PE-RLHF updates inline (:class:`SyncUpdater`) or in a thread beside acting (:class:`BackgroundUpdater`).

Both pay for collected frames with updates at a fixed update-to-data ratio: after
``notify_frames(n)`` calls totalling ``F`` frames, at most ``floor(updates_per_step * F)``
updates have run (:func:`pe_rlhf.runtime.update.update` on ``replay.sample()``), so the learner
never runs ahead of the data. The trainer drives either through the same calls::

    with updater:                                # start(); on exit stop(): owed updates finish
        collector = Collector(env, updater.policy, ...)
        for batch in collector:
            with updater.lock:
                replay.extend(batch)
            updater.notify_frames(batch.numel())
            losses = updater.latest_losses()
            with updater.paused():               # no update in flight: evaluate, checkpoint
                ...

:class:`SyncUpdater` runs the owed updates inside ``notify_frames`` (acting waits: the recipe's
behaviour with simulated mentors). :class:`BackgroundUpdater` runs them in a daemon thread while
the collector keeps stepping the env, so a person driving at a fixed frame rate never sees the
display stall for an update burst (torch ops release the GIL, so the thread overlaps the env).

The learner on a device (``device="cuda"``, ``optim.device``): the loss module (actor, critics, targets)
lives there, each replay sample is moved there, and acting runs a CPU copy of the actor
(``acting_actor``, also the one to evaluate) whose weights are copied from the learner's after every
round of updates, as TorchRL collectors sync policy weights. With ``device=None`` the learner's own actor
acts (SyncUpdater) and nothing is copied.
"""

from __future__ import annotations

import contextlib
import copy
import fractions
import sys
import threading
import time
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from pe_rlhf.runtime.update import update
from pe_rlhf.threads import torch_threads


def _ratio(updates_per_step: float | fractions.Fraction) -> fractions.Fraction:
    """Exact UTD ratio (5 updates per 50 frames is 1/10, not 0.1000000000000000055)."""
    if isinstance(updates_per_step, bool) or not isinstance(updates_per_step, (int, float, fractions.Fraction)):
        raise TypeError(f"updates_per_step must be a number, got {updates_per_step!r}")
    ratio = fractions.Fraction(updates_per_step).limit_denominator(1_000_000)
    if ratio <= 0:
        raise ValueError(f"updates_per_step must be > 0, got {updates_per_step!r}")
    return ratio


class _Updater:
    """What both learners share: the UTD budget, counters, the latest losses."""

    def __init__(self, loss, optimizers: dict, soft_update, replay, *, updates_per_step,
                 max_grad_norm: float | None, threads, precision: str = "fp32", device=None):
        self.loss, self.optimizers, self.soft_update, self.replay = loss, optimizers, soft_update, replay
        self.device = None if device is None else torch.device(device)  # None: where the loss already is
        self.precision = str(precision)  # "fp32" | "bf16": update()'s autocast (pe_rlhf.modules.precision)
        self.updates_per_step = _ratio(updates_per_step)
        self.max_grad_norm = None if max_grad_norm is None else float(max_grad_norm)
        # an int, or a callable answering the count for each round of updates (pe_rlhf.threads.FreeCores)
        self._thread_budget = threads if callable(threads) else None
        self.threads = max(1, int(threads() if callable(threads) else threads))
        self.lock = threading.Lock()  # replay-buffer extends/samples and the acting actor's weights
        self.frames = 0
        self._done = 0
        self.update_seconds = 0.0  # time spent in updates (sample + update), summed
        self._losses: dict[str, float] = {}

    @property
    def updates_done(self) -> int:
        return self._done

    @property
    def updates_owed(self) -> int:
        """``floor(updates_per_step * frames)``: the updates the frames so far pay for."""
        return int(self.updates_per_step * self.frames)

    @property
    def backlog(self) -> int:
        """Updates owed but not run yet (0 for :class:`SyncUpdater` between calls)."""
        return self.updates_owed - self._done

    def _update_once(self) -> dict[str, float]:
        t = time.perf_counter()
        with self.lock:
            sample = self.replay.sample()
        if self.device is not None:
            sample = sample.to(self.device, non_blocking=True)
        losses = update(self.loss, self.optimizers, self.soft_update, sample, self.max_grad_norm, self.precision)
        self.update_seconds += time.perf_counter() - t
        return losses

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.stop(finish=exc_type is None)


class SyncUpdater(_Updater):
    """Updates in the caller's thread: ``notify_frames(n)`` runs the owed updates before returning.

    ``policy`` is the actor itself (nothing runs concurrently with acting); updates run on
    ``threads`` intra-op threads (acting stays on its own count once they return): an int, or a callable
    asked before each round of updates (:class:`~pe_rlhf.threads.FreeCores`: the cores other processes
    leave free), the count of the last round in ``threads``.
    """

    def __init__(self, loss, optimizers: dict, soft_update, replay, *, updates_per_step, max_grad_norm,
                 actor, threads: int | None = None, precision: str = "fp32", device=None):
        super().__init__(loss, optimizers, soft_update, replay, updates_per_step=updates_per_step,
                         max_grad_norm=max_grad_norm, threads=threads or torch.get_num_threads(), precision=precision,
                         device=device)
        self.actor = actor
        self.acting_actor = actor
        if self.device is not None:  # acting on the CPU: a copy, synced after each round of updates
            self.acting_actor = copy.deepcopy(actor).to("cpu").requires_grad_(False)
            self._learner_weights = TensorDict.from_module(actor).data
            self._acting_weights = TensorDict.from_module(self.acting_actor).data
        self.policy = self.acting_actor

    def start(self) -> None:
        pass

    def notify_frames(self, n: int) -> None:
        self.frames += int(n)
        if self.backlog <= 0:
            return
        if self._thread_budget is not None:
            self.threads = max(1, int(self._thread_budget()))
        with torch_threads(self.threads):
            while self._done < self.updates_owed:
                self._losses = self._update_once()
                self._done += 1
        if self.device is not None:
            self._acting_weights.update_(self._learner_weights)

    def latest_losses(self) -> dict[str, float]:
        return dict(self._losses)

    def paused(self):
        return contextlib.nullcontext()

    def stop(self, finish: bool = True) -> None:
        pass


class LockedPolicy(TensorDictModuleBase):
    """The acting actor, run under ``lock`` so it never reads weights the learner is copying in.

    Reads the wrapped actor's ``in_keys`` and writes its ``out_keys`` (for the recipe's actor:
    ``observation`` -> ``loc``, ``scale``, ``action``).
    """

    def __init__(self, actor: TensorDictModuleBase, lock: threading.Lock):
        super().__init__()
        self.actor = actor
        self.in_keys, self.out_keys = list(actor.in_keys), list(actor.out_keys)
        self._lock = lock

    def forward(self, tensordict: TensorDictBase, *args, **kwargs) -> TensorDictBase:
        with self._lock:
            return self.actor(tensordict, *args, **kwargs)


class BackgroundUpdater(_Updater):
    """Updates in a daemon thread, decoupled from acting (see the module docstring).

    Two actors: the loss trains ``actor`` (the learner's, only the thread touches it while it
    runs) and the collector acts with ``policy``, a :class:`LockedPolicy` over a private copy.
    Every ``publish_every`` updates the thread copies the learner's weights into the copy under
    ``lock``; the policy's forward holds the same lock. The alternative (acting and updating one
    actor, the lock held for a whole update) would block a step for up to an update (25-60 ms on
    two cores); here acting waits at most for a weight copy (~45 us for the 256x256 actor) or a
    replay sample. ``replay.extend`` on the acting side and ``replay.sample`` in the thread share the lock.

    Threads: ``torch.set_num_threads`` sets the *calling thread's* intra-op count (an OpenMP
    per-thread setting plus MKL's thread-local one; checked: the main thread keeps 1 while the
    learner sets 2), so the thread sets ``threads`` for itself and acting keeps its single thread.
    The trainer gives it the cores acting does not use (``total - 1``, at least 1): a second learner
    thread would compete with the env step for the same two cores (on cores kept busy by another
    process, a batch-256 update took 50 ms on one thread and 330 ms on two).

    TensorDict's exploration mode (``set_exploration_type``) is one process-wide value; the loss
    sets RANDOM around its actor sampling and restores the previous value, which from another
    thread can switch the collector's rollout mode mid-batch. :meth:`start` therefore makes it
    per-thread (:func:`make_interaction_type_thread_local`); single-threaded code sees no change.

    The GIL: a thread woken from sleep waits up to the interpreter's switch interval (5 ms by
    default) for the GIL while the learner runs Python code. While running, the updater lowers the
    (process-wide) interval to ``switch_interval`` (1 ms) and restores it at :meth:`stop` (one 20 s
    comparison at 10 Hz on two busy cores, ``benchmarks/realtime_jitter.py``: frame jitter p95 6.6 ->
    4.0 ms, p99 10.6 -> 5.7 ms, late frames 4 -> 0 of 199).

    Errors in the thread (e.g. ``FloatingPointError`` from a non-finite loss) stop it and are
    re-raised in the caller by the next ``notify_frames``, ``latest_losses``, ``paused`` or ``stop``.
    Async runs are not bit-reproducible: update timing and the RNG stream interleave with acting.
    """

    def __init__(self, loss, optimizers: dict, soft_update, replay, *, updates_per_step, max_grad_norm,
                 actor, threads: int | None = None, publish_every: int = 1, switch_interval: float | None = 0.001,
                 precision: str = "fp32", device=None):
        super().__init__(loss, optimizers, soft_update, replay, updates_per_step=updates_per_step,
                         max_grad_norm=max_grad_norm, precision=precision, device=device,
                         threads=threads if threads is not None else max(1, torch.get_num_threads() - 1))
        if int(publish_every) < 1:
            raise ValueError(f"publish_every must be >= 1 updates, got {publish_every!r}")
        self.publish_every = int(publish_every)
        self.switch_interval = switch_interval
        self._previous_switch_interval: float | None = None
        self.actor = actor
        self.acting_actor = copy.deepcopy(actor).to("cpu")
        self.acting_actor.requires_grad_(False)
        self.policy = LockedPolicy(self.acting_actor, self.lock)
        self._learner_weights = TensorDict.from_module(actor).data
        self._acting_weights = TensorDict.from_module(self.acting_actor).data
        self._cond = threading.Condition()
        self._in_update = threading.Lock()  # held during each update; paused() takes it
        self._stop_now = self._stop_when_idle = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    # -- the acting side -------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("BackgroundUpdater already started")
        make_interaction_type_thread_local()
        if self.switch_interval is not None:
            self._previous_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(self._previous_switch_interval, float(self.switch_interval)))
        self._stop_now = self._stop_when_idle = False
        self._thread = threading.Thread(target=self._run, name="pe_rlhf-learner", daemon=True)
        self._thread.start()

    def notify_frames(self, n: int) -> None:
        """``n`` more frames are in the replay buffer: the thread may run the updates they pay for."""
        self._raise_if_failed()
        with self._cond:
            self.frames += int(n)
            self._cond.notify_all()

    def latest_losses(self) -> dict[str, float]:
        self._raise_if_failed()
        with self._cond:
            return dict(self._losses)

    @contextlib.contextmanager
    def paused(self):
        """No update runs inside the block (waits for the one in flight): evaluate or checkpoint the
        learner's actor, loss, optimisers and replay buffer. Do not call ``stop`` inside it."""
        self._raise_if_failed()
        with self._in_update:
            if self.device is not None:  # the CPU copy is what gets evaluated: bring it up to date
                self._publish()
            yield

    def stop(self, finish: bool = True) -> None:
        """Join the thread: after the owed updates (``finish``) or after the one in flight; the acting
        copy then holds the learner's weights. Re-raises the thread's error, if any."""
        if self._thread is not None:
            with self._cond:
                self._stop_when_idle = True
                self._stop_now = self._stop_now or not finish
                self._cond.notify_all()
            self._thread.join()
            self._thread = None
            if self._previous_switch_interval is not None:
                sys.setswitchinterval(self._previous_switch_interval)
                self._previous_switch_interval = None
        self._raise_if_failed()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.stop(finish=True)
            return
        with contextlib.suppress(BaseException):  # the exception in flight is the one to report
            self.stop(finish=False)

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise self._error

    # -- the learner thread ----------------------------------------------------------------
    def _run(self) -> None:
        torch.set_num_threads(self.threads)  # this thread's count only (see the class docstring)
        try:
            while self._next_update_due():
                with self._in_update:
                    losses = self._update_once()
                with self._cond:
                    self._done += 1
                    self._losses = losses
                if self._done % self.publish_every == 0:
                    self._publish()
            self._publish()
        except BaseException as e:  # noqa: BLE001 - handed to the acting thread
            self._error = e

    def _next_update_due(self) -> bool:
        """Block until an update is owed (True) or the updater is told to stop (False)."""
        with self._cond:
            while True:
                if self._stop_now:
                    return False
                if self._done < self.updates_owed:
                    return True
                if self._stop_when_idle:
                    return False
                self._cond.wait()

    def _publish(self) -> None:
        with self.lock:
            self._acting_weights.update_(self._learner_weights)


_interaction_type_patch_lock = threading.Lock()


class _ThreadLocalMode(threading.local):
    """Drop-in for tensordict's ``_ContextManager`` whose mode is per thread (None in a new thread)."""

    def __init__(self):
        self.mode: Any = None

    def get_mode(self) -> Any:
        return self.mode

    def set_mode(self, mode: Any) -> None:
        self.mode = mode


def make_interaction_type_thread_local() -> None:
    """Make ``set_exploration_type`` / ``exploration_type()`` per thread, for this process (idempotent).

    TensorDict keeps the interaction type in one module-level holder that ``set_interaction_type``
    writes and restores; two threads entering and leaving it interleave each other's values. The
    holder is replaced by a thread-local one, the calling thread keeping its current value.
    """
    from tensordict.nn import probabilistic

    with _interaction_type_patch_lock:
        current = probabilistic._interaction_type
        if isinstance(current, _ThreadLocalMode):
            return
        if not (hasattr(current, "get_mode") and hasattr(current, "set_mode")):
            raise RuntimeError("tensordict.nn.probabilistic._interaction_type changed shape; cannot make the "
                               "exploration type per-thread (needed by BackgroundUpdater)")
        local = _ThreadLocalMode()
        local.set_mode(current.get_mode())
        probabilistic._interaction_type = local


__all__ = ["BackgroundUpdater", "LockedPolicy", "SyncUpdater", "make_interaction_type_thread_local"]
