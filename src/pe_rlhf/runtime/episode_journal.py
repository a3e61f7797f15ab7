"""``PendingEpisodesJournal``: write every episode that ends inside the batch being collected, at once.

The batch journal (:mod:`pe_rlhf.runtime.journal`) gets a batch when the collector hands it over,
every ``collector.frames_per_batch`` steps; a kill before that would lose the episodes that already
ended inside the batch, a person's finished work. Appended as the training env's last transform,
this one keeps a copy of each step of the current batch and, when a step ends an episode (``("next",
"done")``), writes the batch's steps so far as a pending file (:meth:`BatchJournal.write_pending`:
atomic, checksummed, with the RNG state and the ``state()`` of that moment: the
``InterventionTransform``'s step count and the mentor's state). ``--resume`` completes that file's steps
to a whole batch (:meth:`restart` takes them, so a second kill keeps them too) and trains on it; the
trainer deletes the file once the whole batch is journaled.

A step's copy holds what the collector's batch holds for it: the root entries of the step's input
(``observation``, done flags, the policy's ``action``/``loc``/``scale``, ``("collector",
"traj_ids")``, ...), copied in :meth:`_inv_call` before any other transform sees the action (the
``InterventionTransform`` replaces ``action`` with the executed one for the simulator only), and
the step's output under ``"next"``, copied in :meth:`_step` after every other transform wrote to it
(hence: last). Reads those keys, writes none, changes no spec. The frame count follows the
collector's: batches end on the ``frames_per_batch`` grid (a collection that starts off it, at
``start_frames`` set by :meth:`restart` before the collector is built, first tops its batch up to the
grid); resets are not frames.

Single env only (the ``single`` backend): in the multi-worker backends each worker's env would need
its own journal and a frame count of its share; they are not covered (a kill loses the batch being
collected there).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import Transform

from pe_rlhf.runtime.journal import BatchJournal

__all__ = ["PendingEpisodesJournal"]


class PendingEpisodesJournal(Transform):
    """Journal the current batch's steps up to each episode end (see the module docstring).

    Reads every root entry of a step's input but ``"next"`` and every entry of its output (``("next",
    "done")`` (1,) bool decides); writes no key. A pending file holds a ``(k,)`` TensorDict of those
    entries, ``k`` the steps from the batch's start to the episode's end.

    Args:
        journal: where the pending files go (the run's :class:`~pe_rlhf.runtime.journal.BatchJournal`).
        frames_per_batch: the collector's ``frames_per_batch``.
        state: called at each episode end for the JSON-serialisable actor state stored with the steps
            (None: ``{}``).
        start_frames: the run's frame count when the collector starts (see :meth:`restart`).
    """

    def __init__(self, journal: BatchJournal, frames_per_batch: int,
                 state: Callable[[], dict[str, Any]] | None = None, start_frames: int = 0):
        if int(frames_per_batch) < 1:
            raise ValueError(f"frames_per_batch must be >= 1, got {frames_per_batch!r}")
        super().__init__(in_keys=[], out_keys=[])
        self.journal, self.frames_per_batch, self.state = journal, int(frames_per_batch), state
        self.restart(start_frames)

    def restart(self, start_frames: int, steps: TensorDictBase | None = None) -> None:
        """A collector starts at frame ``start_frames`` (after ``steps``: a ``(k,)`` TensorDict of the batch's
        first steps, a killed run's pending file that this collection completes): forget the steps kept so far."""
        self.batch_start = int(start_frames)
        self._steps: list[TensorDictBase] = list(steps.unbind(0)) if steps is not None else []
        self._root: TensorDictBase | None = None

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._root = tensordict.exclude("next").clone()  # the agent's proposal, before a takeover replaces it
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if next_tensordict.batch_dims:
            raise ValueError(f"PendingEpisodesJournal journals one env; got batch size {next_tensordict.batch_size}")
        step = self._root if self._root is not None else tensordict.exclude("next").clone()
        step.set("next", next_tensordict.clone())
        self._steps.append(step)
        self._root = None
        if bool(next_tensordict.get("done").any()):
            self.journal.write_pending(torch.stack(self._steps), self.batch_start,
                                       self.state() if self.state is not None else {})
        if (self.batch_start + len(self._steps)) % self.frames_per_batch == 0:  # the collector hands it over now
            self.batch_start += len(self._steps)
            self._steps = []
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._root = None  # a reset is no frame: the steps of the batch so far stay
        return tensordict_reset

    def __repr__(self) -> str:
        return f"{type(self).__name__}(frames_per_batch={self.frames_per_batch}, batch_start={self.batch_start})"
