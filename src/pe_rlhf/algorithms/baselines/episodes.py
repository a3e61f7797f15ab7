"""Training episodes seen through a single-env collector's batches: returns, costs, successes, the cost window.

A ``Collector`` over one env yields consecutive ``(T,)`` runs of steps; an episode can start in one batch
and end in a later one. :class:`EpisodeTracker` carries the running sums across batches and records each
episode when its ``("next", "done")`` step arrives.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict import TensorDictBase


@dataclass
class BatchEpisodes:
    """What one batch brought: its steps and summed cost, and the episodes that ended in it."""

    steps: int
    cost: float
    returns: list[float] = field(default_factory=list)
    costs: list[float] = field(default_factory=list)
    successes: list[bool] = field(default_factory=list)
    sim_errors: int = 0


class EpisodeTracker:
    """Per-episode return, cost and success of a single env's batches, and totals over the run.

    Reads, under ``next`` (flat ``(T,)`` batch, shapes ``(T, 1)``): ``reward``, ``cost``, ``done``,
    ``success`` and ``sim_error`` (an episode the simulator's fault ended). ``window`` keeps the costs of
    the last ``window`` finished episodes: the Lagrange multiplier's and CPO's measure of ``J_c``.
    ``state_dict()`` / ``load_state_dict()`` are JSON-ready (checkpoints).
    """

    def __init__(self, window: int = 10):
        self.window: deque[float] = deque(maxlen=int(window))
        self.running_return = self.running_cost = 0.0
        self.steps = self.episodes = self.successes = self.sim_errors = 0
        self.safety_violations = 0.0

    def add(self, batch: TensorDictBase) -> BatchEpisodes:
        nxt = batch.get("next")
        reward = nxt.get("reward").reshape(-1).double()
        cost = nxt.get("cost").reshape(-1).double()
        done = nxt.get("done").reshape(-1)
        success = nxt.get("success").reshape(-1)
        sim_error = nxt.get("sim_error", torch.zeros_like(done)).reshape(-1)
        out = BatchEpisodes(steps=int(done.numel()), cost=float(cost.sum()))
        start = 0
        for end in done.nonzero().squeeze(-1).tolist():
            out.returns.append(self.running_return + float(reward[start:end + 1].sum()))
            out.costs.append(self.running_cost + float(cost[start:end + 1].sum()))
            out.successes.append(bool(success[end]))
            out.sim_errors += int(sim_error[end])
            self.running_return = self.running_cost = 0.0
            start = end + 1
        self.running_return += float(reward[start:].sum())
        self.running_cost += float(cost[start:].sum())
        self.window.extend(out.costs)
        self.steps += out.steps
        self.episodes += len(out.returns)
        self.successes += sum(out.successes)
        self.sim_errors += out.sim_errors
        self.safety_violations += out.cost
        return out

    def window_cost(self) -> float | None:
        """Mean cost of the last ``window`` finished episodes; None before the first one ends."""
        return float(np.mean(self.window)) if self.window else None

    def reset_running(self) -> None:
        """Forget the episode in progress (a resumed run's collector starts a new one)."""
        self.running_return = self.running_cost = 0.0

    @property
    def success_rate(self) -> float:
        """Successes over finished training episodes (0 before the first one ends)."""
        return self.successes / max(self.episodes, 1)

    def state_dict(self) -> dict:
        return {"window": list(self.window), "window_size": self.window.maxlen,
                "running_return": self.running_return, "running_cost": self.running_cost, "steps": self.steps,
                "episodes": self.episodes, "successes": self.successes, "sim_errors": self.sim_errors,
                "safety_violations": self.safety_violations}

    def load_state_dict(self, state: dict) -> None:
        self.window = deque(state["window"], maxlen=self.window.maxlen)
        for key in ("running_return", "running_cost", "safety_violations"):
            setattr(self, key, float(state[key]))
        for key in ("steps", "episodes", "successes", "sim_errors"):
            setattr(self, key, int(state[key]))


def batch_log(tracker: EpisodeTracker, episodes: BatchEpisodes) -> dict[str, float]:
    """The training columns of one iteration (names follow :mod:`pe_rlhf.runtime.plots`): the mean return
    and cost of the episodes that ended in the batch (absent when none did), the run's totals."""
    log = {"train/safety_violations_total": tracker.safety_violations,
           "train/success_rate_total": tracker.success_rate,
           "train/episodes_total": float(tracker.episodes),
           "train/sim_errors_total": float(tracker.sim_errors),
           "train/batch_cost": episodes.cost}
    if episodes.returns:
        log["train/episode_return"] = float(np.mean(episodes.returns))
        log["train/episode_cost"] = float(np.mean(episodes.costs))
        log["train/episode_success_rate"] = float(np.mean(episodes.successes))
    window = tracker.window_cost()
    if window is not None:
        log["train/episode_cost_window"] = window
    return log
