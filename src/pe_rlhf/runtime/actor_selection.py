"""Picking a run's actor on TRAIN scenes: the best of its periodic snapshots, not merely the last.

A reward-free learner can lose in its last few thousand frames what it had learned (issue 17's late collapses: a
seed at 0.62 test success at 20K frames read 0.00 at 30K, and a continuation of the same 20K checkpoint did not
collapse). :class:`ActorSelection` evaluates the actor every ``actor_selection.every_frames`` on the first
``actor_selection.episodes`` scenes of the TRAIN split, never the test scenes (they are for the final
evaluation only); default all 50, since a pick on the first 20 disagreed with the other 30 train scenes in 2 of
4 cells (``docs/results/claims/README.md``). It keeps a copy of the best one, and at the finish the run
evaluates both the last and the picked actor on ``eval.split``; the picked one becomes ``actor.safetensors`` and
``final_eval.json``, the last one's summary is kept beside it (``final_eval.json["last_actor"]``), so every run
measures what the pick changed.

Best: the highest success rate; among equal ones the highest mean route completion; among equal ones the later
snapshot. The copy and the scores are part of every checkpoint (module ``selected_actor``), so ``--resume``
picks as the uninterrupted run would.
"""

from __future__ import annotations

import copy

import torch

from pe_rlhf.envs import scene_seeds

SELECTED_MODULE = "selected_actor"


class ActorSelection:
    """The best actor seen so far on ``episodes`` train scenes (module docstring).

    ``consider(actor, step, summary)`` takes an evaluation summary (``success_rate`` and ``route_completion``,
    each ``{"mean", "std"}``, as :func:`pe_rlhf.evaluation.evaluate` returns) of ``actor`` at ``step``.
    """

    def __init__(self, actor: torch.nn.Module, every: int, episodes: int, split: str = "train"):
        if split != "train":
            raise ValueError(f"ActorSelection(split={split!r}): the actor is picked on train scenes only "
                             "(the test scenes are for the final evaluation); allowed: 'train'")
        if not 1 <= int(episodes) <= len(scene_seeds(split)):
            raise ValueError(f"actor_selection.episodes={episodes}: allowed 1 to {len(scene_seeds(split))} (the "
                             f"{split} scenes)")
        self.every, self.episodes, self.split = int(every), int(episodes), split
        self.actor = copy.deepcopy(actor).requires_grad_(False)  # holds the picked weights
        self.scores: dict[int, tuple[float, float]] = {}  # step -> (success rate, route completion)
        self.step: int | None = None  # the picked snapshot's step

    def key(self, step: int) -> tuple[float, float, int]:
        success, completion = self.scores[step]
        return success, completion, step

    def consider(self, actor: torch.nn.Module, step: int, summary: dict) -> bool:
        """Score ``actor`` at ``step``; keep a copy if it is the best so far. Returns whether it was kept."""
        step = int(step)
        self.scores[step] = (float(summary["success_rate"]["mean"]), float(summary["route_completion"]["mean"]))
        if self.step is not None and self.key(step) < self.key(self.step):
            return False
        self.actor.load_state_dict(actor.state_dict())
        self.step = step
        return True

    def row(self) -> dict[str, float]:
        """The metrics row's ``actor_selection/*`` columns after the latest evaluation."""
        latest = max(self.scores)
        success, completion = self.scores[latest]
        return {"actor_selection/success_rate": success, "actor_selection/route_completion": completion,
                "actor_selection/picked_step": float(self.step)}

    def state_dict(self) -> dict:
        """The scores and the picked step (JSON); the weights travel as the checkpoint's module ``selected_actor``."""
        return {"scores": {str(k): list(v) for k, v in self.scores.items()}, "step": self.step}

    def load_state_dict(self, state: dict) -> None:
        self.scores = {int(k): (float(v[0]), float(v[1])) for k, v in state["scores"].items()}
        self.step = None if state["step"] is None else int(state["step"])

    def summary(self) -> dict:
        """What ``final_eval.json["actor_selection"]`` records."""
        return {"split": self.split, "episodes": self.episodes, "every": self.every, "picked_step": self.step,
                "scores": {str(k): {"success_rate": v[0], "route_completion": v[1]} for k, v in self.scores.items()}}


__all__ = ["SELECTED_MODULE", "ActorSelection"]
