"""Fitting the Q-ensemble estimator on warm-up data (PE-RLHF, Sec. "Ensemble of estimator Q-networks").

The paper trains K critics ``Q_k`` (same architecture, different init) on the warm-up data with
the environment reward::

    L = E[(y - mean_k Q_k(s, a))^2],   y = r + gamma * mean_k Q'_k(s', a'),
    a' ~ pi_expert(s') + N(0, sigma)

so ``Q`` estimates the value of the warm-up (expert / physics) policy. ``fit_q_ensemble`` does
that with a Polyak-averaged target copy ``Q'`` and clipped target-action noise, reading the
warm-up policy's action at ``s'`` from the data (``add_next_actions`` builds it from recorded
trajectories).

``loss="mean"`` is the paper's form: only the members' *mean* is regressed to ``y``. Every member
receives the same residual, so nothing pulls a single member towards ``y``: the members are not
individually Q estimates, and their disagreement is an artefact of init and of that shared
gradient (it typically *grows* during the fit) rather than a measure of what the data leaves
unknown. ``loss="member"`` regresses each member to ``y`` (mean over members of the squared
errors): every member is a Q estimate, they agree where the data pins them down and stay diverse
where it does not (the usual ensemble / REDQ recipe), so the spread is usable by
``HybridActionSelector(variance_threshold=...)``. The means learned by both are comparably good.
Measured on the toy contextual bandit of ``tests/modules/test_q_ensemble.py`` (K=5, 300 steps, true
Q = r): held-out MSE of the mean 0.031 ("mean") vs 0.045 ("member"), from 4.8 at init; per-member
MSE 1.37 vs 0.054; member spread (std over k) on the data 1.06 vs 0.095 (0.08 at init: "mean"
inflated it ~13x), off the data 4.6 vs 0.41. Both spreads grow off the data, but with "mean" the
on-data spread is as large as the Q differences the selector compares.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from pe_rlhf.modules.q_ensemble import QEnsemble

__all__ = ["add_next_actions", "fit_q_ensemble"]

_REQUIRED = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "terminated"))


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


def _check_args(steps, batch_size, gamma, lr, target_noise, tau, loss):
    if not isinstance(steps, int) or steps < 0:
        raise ValueError(f"fit_q_ensemble: steps={steps!r} must be an int >= 0")
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"fit_q_ensemble: batch_size={batch_size!r} must be an int >= 1")
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"fit_q_ensemble: gamma={gamma} must be in [0, 1]")
    if not lr > 0:
        raise ValueError(f"fit_q_ensemble: lr={lr} must be > 0")
    if not target_noise >= 0:
        raise ValueError(f"fit_q_ensemble: target_noise={target_noise} must be >= 0")
    if not 0.0 < tau <= 1.0:
        raise ValueError(f"fit_q_ensemble: tau={tau} must be in (0, 1]")
    if loss not in ("mean", "member"):
        raise ValueError(f"fit_q_ensemble: loss={loss!r} must be 'mean' or 'member'")


def _make_target(ensemble: QEnsemble) -> QEnsemble:
    target = QEnsemble(**ensemble.config)
    target.load_state_dict(ensemble.state_dict())
    target = target.to(next(ensemble.parameters()).device)
    target.requires_grad_(False)
    return target


def fit_q_ensemble(
    ensemble: QEnsemble,
    data: Any,
    *,
    steps: int,
    batch_size: int = 256,
    gamma: float = 0.99,
    lr: float = 3e-4,
    target_noise: float = 0.1,
    tau: float = 0.005,
    loss: str = "mean",
    next_action_key: NestedKey = ("next", "action"),
    seed: int = 0,
    progress: bool = False,
) -> dict[str, Any]:
    """Train ``ensemble`` in place for ``steps`` Adam steps of TD regression on ``data``.

    ``data`` is a TorchRL replay buffer (anything with ``sample(batch_size)`` returning a
    TensorDict) or a TensorDict of transitions (any batch shape; flattened) with
    ``observation``, ``action``, ``("next", "observation")``, ``("next", "reward")``,
    ``("next", "terminated")`` and the warm-up policy's action at ``s'`` under
    ``next_action_key`` (see ``add_next_actions``). Per step, on a uniform minibatch::

        a'  = clip(a_next + N(0, target_noise), -1, 1)
        y   = r + gamma * (1 - terminated) * mean_k Q'_k(s', a')      (no gradient)
        L   = (y - mean_k Q_k(s, a))^2                 loss="mean"   (the paper's)
        L   = mean_k (y - Q_k(s, a))^2                 loss="member" (keeps members diverse)

    ``Q'`` is a Polyak copy (``Q' <- (1 - tau) Q' + tau Q`` after each step). Randomness
    (minibatches, noise) comes from ``torch.manual_seed(seed)`` inside ``torch.random.fork_rng``,
    so the global RNG is left untouched; a replay buffer's own sampler draws from that same
    forked RNG. Works on a frozen (``requires_grad_(False)``) ensemble: the flags are turned on
    for the fit and restored afterwards. Replay-buffer priorities are not updated.

    Returns ``{"final_loss", "mean_loss", "first_loss", "steps", "loss", "loss_history"}``
    (losses as floats, NaN when ``steps == 0``; ``loss_history`` a CPU tensor ``(steps,)``).
    """
    _check_args(steps, batch_size, gamma, lr, target_noise, tau, loss)
    if not isinstance(ensemble, QEnsemble):
        raise TypeError(f"fit_q_ensemble expects a QEnsemble, got {type(ensemble).__name__}")
    keys = list(_REQUIRED) + [next_action_key]
    device = next(ensemble.parameters()).device

    if isinstance(data, TensorDictBase):
        missing = [k for k in keys if k not in data.keys(include_nested=True)]
        if missing:
            raise KeyError(f"fit_q_ensemble: data lacks {missing} (has {sorted(map(str, data.keys(True, True)))}); "
                           "for recorded trajectories, add_next_actions(td) builds ('next', 'action')")
        flat = data.select(*keys).reshape(-1)
        if flat.numel() == 0:
            raise ValueError("fit_q_ensemble: data holds no transitions")
        flat = flat.to(device)

        def sample():
            return flat[torch.randint(flat.shape[0], (batch_size,), device=device)]
    elif hasattr(data, "sample"):
        if hasattr(data, "__len__") and len(data) == 0:
            raise ValueError("fit_q_ensemble: the replay buffer is empty")

        def sample():
            batch = data.sample(batch_size)
            if not isinstance(batch, TensorDictBase):
                raise TypeError(f"fit_q_ensemble: the replay buffer returned {type(batch).__name__}, "
                                "expected a TensorDict")
            missing = [k for k in keys if k not in batch.keys(include_nested=True)]
            if missing:
                raise KeyError(f"fit_q_ensemble: replay-buffer samples lack {missing}")
            return batch.select(*keys).reshape(-1).to(device)
    else:
        raise TypeError(f"fit_q_ensemble: data must be a TensorDict or a replay buffer, got {type(data).__name__}")

    history = torch.zeros(steps, device=device)
    params = list(ensemble.parameters())
    flags = [p.requires_grad for p in params]
    fork_devices = [device] if device.type == "cuda" else []
    report_every = max(1, steps // 10)
    try:
        for p in params:
            p.requires_grad_(True)
        optim = torch.optim.Adam(ensemble.ensemble.params_td.parameters(), lr=lr)
        with torch.random.fork_rng(devices=fork_devices):
            torch.manual_seed(seed)
            target = _make_target(ensemble)  # its (overwritten) init draws from the forked RNG
            online_p = [p for _, p in sorted(ensemble.ensemble.params_td.items(True, True), key=lambda kv: str(kv[0]))]
            target_p = [p for _, p in sorted(target.ensemble.params_td.items(True, True), key=lambda kv: str(kv[0]))]
            for step in range(steps):
                batch = sample()
                obs, act = batch.get("observation"), batch.get("action")
                n = obs.shape[0]
                reward = batch.get(("next", "reward")).reshape(n).to(obs.dtype)
                term = batch.get(("next", "terminated")).reshape(n).to(obs.dtype)
                with torch.no_grad():
                    next_act = batch.get(next_action_key)
                    if target_noise > 0:
                        next_act = next_act + target_noise * torch.randn_like(next_act)
                    next_act = next_act.clamp(-1.0, 1.0)
                    q_next = target.values(batch.get(("next", "observation")), next_act).mean(0)
                    y = reward + gamma * (1.0 - term) * q_next
                q = ensemble.values(obs, act)  # (K, n)
                if loss == "mean":
                    value = (y - q.mean(0)).pow(2).mean()
                else:
                    value = (q - y).pow(2).mean()
                optim.zero_grad(set_to_none=True)
                value.backward()
                optim.step()
                with torch.no_grad():
                    torch._foreach_lerp_(target_p, online_p, tau)
                history[step] = value.detach()
                if progress and ((step + 1) % report_every == 0 or step + 1 == steps):
                    print(f"fit_q_ensemble: step {step + 1}/{steps} loss {value.item():.5f}", flush=True)
    finally:
        for p, flag in zip(params, flags):
            p.requires_grad_(flag)
    hist = history.cpu()
    nan = math.nan
    return {
        "final_loss": hist[-1].item() if steps else nan,
        "mean_loss": hist.mean().item() if steps else nan,
        "first_loss": hist[0].item() if steps else nan,
        "steps": steps,
        "loss": loss,
        "loss_history": hist,
    }


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
