"""A replay buffer that keeps takeover rows apart and gives them a fixed share of every batch (the authors' code).

The authors' learner (their ``utils/replay_buffer.py``) stores transitions the mentor drove in a buffer of their
own and draws ``min(batch_size // 2, len(takeover rows))`` of each batch from it, the rest from the agent's own
rows; a uniform buffer instead gives takeover rows whatever share they hold of everything collected (all of it
during warm-up, a quarter or less late in training). :class:`TakeoverBalancedReplayBuffer` does the former with
``takeover_share=0.5``, as a drop-in for the recipe's ``TensorDictReplayBuffer`` (``extend``, ``sample``,
``len``, ``dumps``/``loads`` for checkpoints).

Keys: a row is a takeover row when ``takeover_key`` (default ``("next", "intervention")``, bool ``(1,)``) is true;
every other key is stored as given. A sampled batch holds the takeover rows first, then the agent's, shape
``(batch_size,)``.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from pe_rlhf.transforms.keys import INTERVENTION


class TakeoverBalancedReplayBuffer:
    """Two ``TensorDictReplayBuffer`` s of ``size`` rows each: takeover rows and the agent's own. ``sample()`` draws
    ``min(round(batch_size * takeover_share), takeover rows stored)`` rows from the first and the rest from the
    second (all of them from the takeover rows while the agent has none)."""

    def __init__(self, size: int, batch_size: int, takeover_share: float = 0.5,
                 takeover_key: str | tuple[str, ...] = ("next", INTERVENTION)):
        if not 0.0 <= float(takeover_share) <= 1.0:
            raise ValueError(f"TakeoverBalancedReplayBuffer takeover_share={takeover_share!r} is invalid: "
                             f"a share in [0, 1]")
        self.batch_size, self.takeover_share, self.takeover_key = int(batch_size), float(takeover_share), takeover_key
        self.takeover = TensorDictReplayBuffer(storage=LazyTensorStorage(int(size)))
        self.agent = TensorDictReplayBuffer(storage=LazyTensorStorage(int(size)))

    def __len__(self) -> int:
        return len(self.takeover) + len(self.agent)

    def extend(self, rows: TensorDictBase) -> None:
        """Store ``rows`` (shape ``(N,)``), each in the buffer its ``takeover_key`` says."""
        mask = rows.get(self.takeover_key).reshape(-1).bool()
        if mask.any():
            self.takeover.extend(rows[mask])
        if not mask.all():
            self.agent.extend(rows[~mask])

    def split(self) -> tuple[int, int]:
        """How many rows of the next batch come from the takeover rows and how many from the agent's."""
        from_takeover = min(round(self.batch_size * self.takeover_share), len(self.takeover))
        if len(self.agent) == 0:
            from_takeover = self.batch_size
        return from_takeover, self.batch_size - from_takeover

    def sample(self) -> TensorDictBase:
        """``batch_size`` rows, the takeover share first (see :meth:`split`)."""
        if len(self) == 0:
            raise RuntimeError("TakeoverBalancedReplayBuffer.sample: the buffer is empty")
        from_takeover, from_agent = self.split()
        parts = [buffer.sample(batch_size=n) for buffer, n in ((self.takeover, from_takeover),
                                                                (self.agent, from_agent)) if n]
        return parts[0] if len(parts) == 1 else torch.cat(parts, 0)

    def empty(self) -> None:
        self.takeover.empty()
        self.agent.empty()

    def dumps(self, path: str | Path) -> None:
        """The non-empty buffers under ``path`` (``takeover/`` and ``agent/``, TorchRL's format)."""
        for name, buffer in self._parts():
            if len(buffer):
                (Path(path) / name).mkdir(parents=True, exist_ok=True)
                buffer.dumps(Path(path) / name)

    def loads(self, path: str | Path) -> None:
        """What :meth:`dumps` wrote; a buffer with no folder there is emptied."""
        for name, buffer in self._parts():
            if (Path(path) / name).is_dir():
                buffer.loads(Path(path) / name)
            else:
                buffer.empty()

    def _parts(self) -> tuple[tuple[str, TensorDictReplayBuffer], ...]:
        return ("takeover", self.takeover), ("agent", self.agent)
