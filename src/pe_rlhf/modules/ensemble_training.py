"""The data and the schedule of the Q-ensemble fit (PE-RLHF, Sec. "Ensemble of estimator Q-networks").

The fit itself is a loss beside the other objectives: :class:`pe_rlhf.objectives.QEnsembleTDLoss` (TD regression
to the value of the warm-up policy) and :func:`pe_rlhf.objectives.fit_q_ensemble` (the loop around it). Here:
``add_next_actions`` writes the policy's action at ``s'`` that the TD target reads, and ``EnsembleSchedule``
says when to fit (once after warm-up, then frozen or refreshed).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = ["EnsembleSchedule", "add_next_actions"]


def add_next_actions(td: TensorDictBase, *, action_key: NestedKey = "action",
                     next_action_key: NestedKey = ("next", "action"),
                     done_key: NestedKey = ("next", "done")) -> TensorDictBase:
    """Write, in place, the policy's action at ``s'`` for each transition of a trajectory.

    ``td`` has the time as its *last* batch dim (``(T,)`` for a flat run of consecutive episodes,
    ``(N, T)`` for a TorchRL rollout of N envs). ``next_action[t] = action[t + 1]`` within an
    episode; where ``done[t]`` (terminated or truncated, the episode boundary) and at the last
    step of the data, the step's own action is used as a stand-in. After a termination the value
    is multiplied by ``1 - terminated`` in the target and does not matter; after a truncation (and
    at the end of the data) it is an approximation of the action the policy would have taken.
    Returns ``td``.
    """
    if td.batch_dims < 1:
        raise ValueError("add_next_actions: td needs a time dimension (batch_size (T,) or (..., T))")
    action = td.get(action_key)
    done = td.get(done_key)
    t_dim = td.batch_dims - 1
    shifted = torch.cat([action.narrow(t_dim, 1, action.shape[t_dim] - 1), action.narrow(t_dim, -1, 1)], t_dim)
    done = done.reshape(*td.batch_size, *([1] * (action.dim() - td.batch_dims))).to(torch.bool)
    td.set(next_action_key, torch.where(done, action, shifted))
    return td


class EnsembleSchedule:
    """When to (re)fit the Q-ensemble: once after warm-up, then frozen or refreshed every N env steps.

    ``refresh_every=0`` (default) freezes the ensemble after the warm-up fit, as in the paper;
    ``refresh_every=N`` refits it (``refresh_steps`` gradient steps, on the data the caller passes:
    e.g. the warm-up buffer plus mentor-executed transitions) every ``N`` env steps after warm-up.
    ``due(env_step)`` is True exactly once per scheduled point; ``state_dict`` keeps the last fit
    step so a resumed run neither repeats nor skips a refresh.
    """

    def __init__(self, warmup_steps: int, refresh_every: int = 0, warmup_fit_steps: int = 2000,
                 refresh_steps: int = 500):
        for name, value in (("warmup_steps", warmup_steps), ("refresh_every", refresh_every),
                            ("warmup_fit_steps", warmup_fit_steps), ("refresh_steps", refresh_steps)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"EnsembleSchedule {name}={value!r} is invalid: must be an int >= 0")
        self.warmup_steps, self.refresh_every = warmup_steps, refresh_every
        self.warmup_fit_steps, self.refresh_steps = warmup_fit_steps, refresh_steps
        self.last_fit: int | None = None

    def due(self, env_step: int) -> int:
        """Gradient steps to fit now (0 if nothing is due); marks the fit as done."""
        if env_step < self.warmup_steps:
            return 0
        if self.last_fit is None:
            self.last_fit = env_step
            return self.warmup_fit_steps
        if self.refresh_every and env_step - self.last_fit >= self.refresh_every:
            self.last_fit = env_step
            return self.refresh_steps
        return 0

    def state_dict(self) -> dict:
        return {"last_fit": self.last_fit}

    def load_state_dict(self, state: dict) -> None:
        self.last_fit = state.get("last_fit")
