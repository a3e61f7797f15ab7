"""``HybridActionSelector``: trust the mentor's action only if the Q-ensemble values it more than physics'."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from pe_rlhf.modules.q_ensemble import QEnsemble

PERSISTENCE = ("off", "latch", "always")  # HybridActionSelector.persistence
REFERENCES = ("physics", "physics_or_recovery")  # HybridActionSelector.reference


class HybridActionSelector(TensorDictModuleBase):
    """``a_hybrid = a_mentor`` iff ``mean_k[Q_k(s, a_mentor) - Q_k(s, a_phy)] >= epsilon_select``, else ``a_phy``.

    Reads ``observation`` ``(*B, obs)``, ``mentor_action`` and ``physics_action`` ``(*B, A)``;
    writes ``hybrid_action`` ``(*B, A)`` and ``mentor_selected`` bool ``(*B, 1)``. Batched: the
    ensemble runs once on both actions (``2 * B`` rows, one vectorised call).

    The value source ``q_ensemble`` is a :class:`~pe_rlhf.modules.QEnsemble` (``values(obs, acts) -> (K, N)``)
    or any module with ``needs_env = True`` and ``values(obs, acts, env=) -> (K, N)`` that forecasts from the
    simulator (:class:`~pe_rlhf.physics.SafetyForecastValue`: seconds until a failure; ``epsilon_select`` is
    then a time). ``forward`` on a tensordict serves the first kind only (it has no simulator).

    A non-finite action (NaN/inf entries) is never chosen over a finite one, whatever the ensemble says.

    ``epsilon_select`` defaults to the paper's table (0.5); the authors' code uses 1.5. Any finite value is
    meaningful, in the value source's units: > 0, the mentor must be valued at least that much above physics
    (doubt favours physics); 0, the higher-valued action wins (a tie keeps the mentor); < 0, the mentor is
    trusted unless physics is valued ``-epsilon_select`` above it (physics as a veto). Past the advantages
    the value source produces, either way, the choice stops depending on the state: always physics (large
    positive) or always the mentor (large negative).
    ``variance_threshold`` (off by default) reproduces that code's escape: the mentor is also
    trusted when the ensemble's standard deviation on the physics action exceeds it (the
    estimator does not know that action well enough to overrule the person).

    ``switch_margin`` (off by default: every step is judged alone, as the paper) makes a takeover's choice
    sticky: given the previous step's choice (``select(..., previous=)``), the selector switches from the
    mentor to physics only when the advantage falls below ``epsilon_select - switch_margin``, and from
    physics to the mentor only when it reaches ``epsilon_select + switch_margin``. One step of braking
    costs little under an expert's continuation, so without it physics can win step after step behind an
    obstacle that the mentor was steering around.

    ``veto_patience`` (1 by default: every step judged alone) lets the mentor keep the wheel through short
    disagreements: physics replaces the mentor only once the value has vetoed it on ``veto_patience``
    consecutive steps of a takeover (counted from ``select(..., previous=None)``, a takeover's start), or at
    once where the mentor's own value is at most ``imminent_failure`` (with the forecast: its action fails within
    that many seconds). A forecast that holds each action 1 s calls the sharpest steps of a lane change a failure
    and hands the next step back; patience keeps such a manoeuvre whole. The count is state of this selector, for
    one takeover at a time (``InterventionTransform``, ``InterventionWrapper``; batched inputs keep one count per
    row, and ``HybridSelectionTransform`` keeps its own count per row); :meth:`streak_state` /
    :meth:`load_streak_state` carry it through a checkpoint.

    ``persistence`` ("off" by default) judges the mentor's action as it will actually be repeated, for a value
    source with ``repeated_values(obs, acts, env=)`` (:class:`~pe_rlhf.physics.SafetyForecastValue`: the action
    held for the whole horizon, no recovery). ``"latch"``: a veto holds; once physics replaced the mentor in a
    takeover, physics keeps the wheel until the mentor's action *repeated* is no worse than physics' by
    ``epsilon_select`` (the latch is the veto count, 1 while held: same state, same checkpointing).
    ``"always"``: every step's mentor action must pass that repeated check as well. A driver that repeats a
    dangerous action passes a one-step check at every step while the sequence ends in a crash; the latch is
    what stops it (``benchmarks/ensemble_selection.py``, docs/guide/shield.md).
    ``latch_release_speed`` (None by default) [m/s], with ``"latch"`` and a value source with ``speed(env=)``: where
    the car is at most this fast, a held veto no longer holds and the step is judged as any other. A sharp manoeuvre
    repeated for the whole horizon always leaves the road: the professional, steering full lock around an obstacle
    at walking pace, was vetoed once and then held behind it, standing, for the rest of the episode.

    ``reference`` ("physics" by default) is what the mentor is compared with: physics' action's value, or
    (``"physics_or_recovery"``, a value source with ``recovery_value(env=)``) the better of it and the value
    of recovering at once. The forecast holds physics' action 1 s as any other, and the sharpest steps of
    physics' own lane change held 1 s leave the road although physics, a closed loop, never holds them: the
    mentor's danger then hides below physics'. Where braking at once is the better of the two, it is also
    what the hybrid executes in physics' place (the value source's ``recovery_action(env=)``;
    ``recovery_value_and_action(env=)``, where it has one, gives both from one forecast; unbatched: the forecast
    reads one simulator).

    ``strict_in_danger`` (off by default): where physics' (the reference's) own value is below the forecast's
    horizon, the mentor needs an advantage of at least 0 whatever ``epsilon_select`` says: a negative epsilon's
    slack, repeated step after step while everything is forecast to fail, ratchets the state down.

    ``progress_margin`` (None by default: safety alone) [m], for a value source with ``progress(obs, acts, env=)``
    (:class:`~pe_rlhf.physics.SafetyForecastValue`: metres along the route an action held ``hold`` seconds
    makes): where physics' action is safe over the whole forecast, the mentor's must also make at least physics'
    progress less ``progress_margin``, or physics drives. A time-to-failure value cannot tell a safe action
    that stops the car from one that drives on: a random mentor, whose actions are rarely forecast to fail,
    kept the wheel 88% of its takeover steps and its mean braking stopped the car
    (docs/experiments/shield-calibration.md).
    """

    def __init__(
        self,
        q_ensemble: QEnsemble | torch.nn.Module,
        epsilon_select: float = 0.5,
        variance_threshold: float | None = None,
        switch_margin: float | None = None,
        veto_patience: int = 1,
        imminent_failure: float | None = None,
        persistence: str = "off",
        reference: str = "physics",
        strict_in_danger: bool = False,
        progress_margin: float | None = None,
        latch_release_speed: float | None = None,
        observation_key: NestedKey = "observation",
        mentor_action_key: NestedKey = "mentor_action",
        physics_action_key: NestedKey = "physics_action",
        out_keys: tuple[NestedKey, NestedKey] = ("hybrid_action", "mentor_selected"),
    ):
        super().__init__()
        if not isinstance(epsilon_select, (int, float)) or not math.isfinite(epsilon_select):
            raise ValueError(f"epsilon_select={epsilon_select!r} must be a finite number")
        if variance_threshold is not None and (
            not isinstance(variance_threshold, (int, float)) or not math.isfinite(variance_threshold)
            or variance_threshold < 0
        ):
            raise ValueError(f"variance_threshold={variance_threshold!r} must be a finite number >= 0, or None")
        if switch_margin is not None and (
            isinstance(switch_margin, bool) or not isinstance(switch_margin, (int, float))
            or math.isnan(switch_margin) or switch_margin < 0
        ):
            raise ValueError(f"switch_margin={switch_margin!r} must be a number >= 0 (inf: never switch), or None")
        self.switch_margin = None if switch_margin is None else float(switch_margin)
        if isinstance(veto_patience, bool) or not isinstance(veto_patience, int) or veto_patience < 1:
            raise ValueError(f"veto_patience={veto_patience!r} must be an integer >= 1 (1: every step judged alone)")
        if imminent_failure is not None and (isinstance(imminent_failure, bool)
                                             or not isinstance(imminent_failure, (int, float))
                                             or not math.isfinite(imminent_failure)):
            raise ValueError(f"imminent_failure={imminent_failure!r} must be a finite number, or None")
        if persistence not in PERSISTENCE:
            raise ValueError(f"persistence={persistence!r} is invalid: allowed {list(PERSISTENCE)}")
        if persistence != "off" and not hasattr(q_ensemble, "repeated_values"):
            raise ValueError(f"persistence={persistence!r} needs a value source with repeated_values (the physics "
                             f"forecast); {type(q_ensemble).__name__} has none")
        if persistence != "off" and veto_patience > 1:
            raise ValueError("persistence and veto_patience > 1 both keep the veto count: use one of them")
        self.persistence = persistence
        if reference not in REFERENCES:
            raise ValueError(f"reference={reference!r} is invalid: allowed {list(REFERENCES)}")
        if reference != "physics" and not hasattr(q_ensemble, "recovery_value"):
            raise ValueError(f"reference={reference!r} needs a value source with recovery_value (the physics "
                             f"forecast); {type(q_ensemble).__name__} has none")
        self.reference = reference
        if strict_in_danger and not hasattr(q_ensemble, "horizon"):
            raise ValueError(f"strict_in_danger needs a value source with a horizon (the physics forecast); "
                             f"{type(q_ensemble).__name__} has none")
        self.strict_in_danger = bool(strict_in_danger)
        if progress_margin is not None and (isinstance(progress_margin, bool)
                                            or not isinstance(progress_margin, (int, float))
                                            or not math.isfinite(progress_margin) or progress_margin < 0):
            raise ValueError(f"progress_margin={progress_margin!r} must be a finite number of metres >= 0, or None")
        if progress_margin is not None and not (hasattr(q_ensemble, "progress") and hasattr(q_ensemble, "horizon")):
            raise ValueError(f"progress_margin needs a value source with progress (the physics forecast); "
                             f"{type(q_ensemble).__name__} has none")
        self.progress_margin = None if progress_margin is None else float(progress_margin)
        if latch_release_speed is not None and (isinstance(latch_release_speed, bool)
                                                or not isinstance(latch_release_speed, (int, float))
                                                or not math.isfinite(latch_release_speed) or latch_release_speed < 0):
            raise ValueError(f"latch_release_speed={latch_release_speed!r} must be a finite speed [m/s] >= 0, or None")
        if latch_release_speed is not None and (persistence != "latch" or not hasattr(q_ensemble, "speed")):
            raise ValueError("latch_release_speed needs persistence='latch' and a value source with speed (the physics "
                             f"forecast); got persistence={persistence!r}, {type(q_ensemble).__name__}")
        self.latch_release_speed = None if latch_release_speed is None else float(latch_release_speed)
        self.veto_patience = veto_patience
        self.imminent_failure = None if imminent_failure is None else float(imminent_failure)
        self._veto_streak: torch.Tensor | None = None
        self.q_ensemble = q_ensemble
        self.epsilon_select = float(epsilon_select)
        self.variance_threshold = variance_threshold
        self.in_keys = [observation_key, mentor_action_key, physics_action_key]
        self.out_keys = list(out_keys)

    @torch.no_grad()
    def select(self, observation: torch.Tensor, mentor_action: torch.Tensor,
               physics_action: torch.Tensor, previous: torch.Tensor | bool | None = None, env=None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(hybrid_action (*B, A), mentor_selected (*B, 1) bool)`` for plain tensors.

        ``previous``: the choice at the previous step of the same takeover (bool, or ``(*B, 1)`` /
        ``(*B,)`` bool; None at a takeover's start); used only with ``switch_margin``. ``env``: the
        simulator, for a value source that forecasts from it (``needs_env``, e.g.
        :class:`~pe_rlhf.physics.SafetyForecastValue`); unbatched then. With ``veto_patience`` > 1 the veto
        count is this selector's (:meth:`select_counted` takes it as an argument instead)."""
        streak = None if previous is None else self._veto_streak  # None: a takeover's start counts from 0
        hybrid, chosen, streak = self.select_counted(observation, mentor_action, physics_action, previous, streak, env)
        if self.veto_patience > 1 or self.persistence != "off":
            self._veto_streak = streak
        return hybrid, chosen

    @torch.no_grad()
    def select_counted(self, observation: torch.Tensor, mentor_action: torch.Tensor, physics_action: torch.Tensor,
                       previous: torch.Tensor | bool | None = None, streak: torch.Tensor | None = None, env=None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`select` without state: ``(hybrid_action, mentor_selected, streak)``.

        ``streak``: each row's count of consecutive vetoes in its takeover before this step, int64 ``(N,)``
        for ``N`` rows (``(1,)`` unbatched); None or another shape: zeros (every row's takeover starts here).
        The returned ``streak`` is the count after this step (used with ``veto_patience`` > 1; without it,
        zeros). ``previous`` serves ``switch_margin`` only."""
        return self.judge(observation, mentor_action, physics_action, previous, streak, env)[:3]

    @torch.no_grad()
    def judge(self, observation: torch.Tensor, mentor_action: torch.Tensor, physics_action: torch.Tensor,
              previous: torch.Tensor | bool | None = None, streak: torch.Tensor | None = None, env=None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`select_counted` and the values it compared: ``(hybrid_action, mentor_selected, streak,
        value_mentor, value_physics)``, the last two float32 ``(N,)`` (the ensemble's mean; with the forecast,
        seconds until each action fails)."""
        obs = torch.cat([observation, observation], 0) if observation.dim() > 1 else torch.stack([observation] * 2)
        acts = torch.cat([mentor_action, physics_action], 0) if mentor_action.dim() > 1 else torch.stack(
            [mentor_action, physics_action])
        if getattr(self.q_ensemble, "needs_env", False):
            if env is None:
                raise ValueError(f"{type(self.q_ensemble).__name__} forecasts from the simulator: "
                                 "pass select(..., env=)")
            q = self.q_ensemble.values(obs, acts, env=env)  # (1, 2)
        else:
            q = self.q_ensemble.values(obs, acts)  # (K, 2B) or (K, 2)
        q_mentor, q_phy = q.chunk(2, dim=1)
        if self.reference == "physics_or_recovery":  # physics is a closed loop: it can always brake now
            physics_action, q_phy = self._better_fallback(physics_action, q_phy, env)
        advantage = (q_mentor - q_phy).mean(0)
        epsilon = self._epsilon(q_phy.mean(0))
        chosen = advantage >= epsilon
        if self.progress_margin is not None:
            chosen = self._progressing(chosen, obs, acts, q_phy.mean(0), env)
        if streak is None or streak.shape != chosen.shape:
            streak = torch.zeros_like(chosen, dtype=torch.long)
        if self.veto_patience > 1:
            chosen, streak = self._patient(chosen, q_mentor.mean(0), streak)
        if self.persistence != "off":
            chosen, streak = self._persistent(chosen, obs, acts, q_phy.mean(0), streak, env)
        if self.switch_margin is not None and previous is not None:
            prev = torch.as_tensor(previous, dtype=torch.bool, device=advantage.device).reshape(advantage.shape)
            stay_mentor = advantage >= self.epsilon_select - self.switch_margin
            move_to_mentor = advantage >= self.epsilon_select + self.switch_margin
            chosen = torch.where(prev, stay_mentor, move_to_mentor)
        if self.variance_threshold is not None:
            chosen = chosen | (q_phy.std(0, unbiased=False) > self.variance_threshold)
        finite_mentor = torch.isfinite(acts[: len(acts) // 2]).all(-1)
        finite_phy = torch.isfinite(acts[len(acts) // 2:]).all(-1)
        chosen = torch.where(finite_mentor != finite_phy, finite_mentor, chosen)
        if mentor_action.dim() == 1:
            chosen = chosen.squeeze(0)
        hybrid = torch.where(chosen.unsqueeze(-1), mentor_action, physics_action)
        return hybrid, chosen.unsqueeze(-1), streak, q_mentor.mean(0), q_phy.mean(0)

    def _patient(self, chosen: torch.Tensor, value_mentor: torch.Tensor, streak: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """Physics replaces the mentor only after ``veto_patience`` consecutive vetoes in a takeover, or at once
        where the mentor's own value is at most ``imminent_failure``; returns the choice and the new count."""
        veto = ~chosen
        streak = torch.where(veto, streak + 1, torch.zeros_like(streak))
        replace = streak >= self.veto_patience
        if self.imminent_failure is not None:
            replace = replace | (veto & (value_mentor <= self.imminent_failure))
        return ~replace, streak

    def _better_fallback(self, physics_action: torch.Tensor, q_phy: torch.Tensor, env
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """Physics' action and value, or the recovery's (braking now) where its value is higher by more than the
        slack ``-epsilon_select`` (one row; braking where physics is only a little worse stops the car for good).
        The value is the better of the two either way."""
        if bool((q_phy >= self.q_ensemble.horizon).all()):
            return physics_action, q_phy  # physics' action is safe over the whole forecast: nothing is better
        both = getattr(self.q_ensemble, "recovery_value_and_action", None)  # both from one forecast
        recovery, action = both(env=env) if both is not None else (self.q_ensemble.recovery_value(env=env), None)
        recovery = recovery.to(q_phy)
        if bool((recovery > q_phy + max(-self.epsilon_select, 0.0)).all()):  # within the slack physics drives on
            action = (self.q_ensemble.recovery_action(env=env) if action is None else action).to(physics_action)
            return action.reshape(physics_action.shape), recovery.expand_as(q_phy)
        return physics_action, torch.maximum(q_phy, recovery)

    def _progressing(self, chosen: torch.Tensor, obs: torch.Tensor, acts: torch.Tensor, value_phy: torch.Tensor,
                     env) -> torch.Tensor:
        """Where physics' action is safe over the whole forecast, the mentor keeps the wheel only if its action
        makes at least physics' progress less ``progress_margin`` (the value source's ``progress``)."""
        need = chosen & (value_phy >= self.q_ensemble.horizon)
        if need.any():
            kwargs = {"env": env} if getattr(self.q_ensemble, "needs_env", False) else {}
            progress = self.q_ensemble.progress(obs, acts, **kwargs).mean(0)
            n = len(acts) // 2
            chosen = torch.where(need, progress[:n] >= progress[n:] - self.progress_margin, chosen)
        return chosen

    def _epsilon(self, value_phy: torch.Tensor) -> torch.Tensor:
        """``epsilon_select`` per row; with ``strict_in_danger``, no slack (at least 0) where physics' own value
        is below the forecast's horizon (the fallback itself is forecast to fail: only a better action wins)."""
        eps = torch.full_like(value_phy, self.epsilon_select)
        if self.strict_in_danger:
            eps = torch.where(value_phy < self.q_ensemble.horizon, eps.clamp(min=0.0), eps)
        return eps

    def _persistent(self, chosen: torch.Tensor, obs: torch.Tensor, acts: torch.Tensor, value_phy: torch.Tensor,
                    streak: torch.Tensor, env) -> tuple[torch.Tensor, torch.Tensor]:
        """The mentor's action repeated over the forecast must be no worse than physics' by ``epsilon_select``:
        at every step (``always``) or while a veto holds (``latch``: ``streak`` 1); returns the choice and the
        new latch (1 where physics drives)."""
        need = chosen if self.persistence == "always" else chosen & (streak > 0)
        if self.latch_release_speed is not None and need.any():  # a standing car: the step is judged alone
            kwargs = {"env": env} if getattr(self.q_ensemble, "needs_env", False) else {}
            need = need & (self.q_ensemble.speed(**kwargs).reshape(-1).to(need.device) > self.latch_release_speed)
        if need.any():
            n = len(acts) // 2
            kwargs = {"env": env} if getattr(self.q_ensemble, "needs_env", False) else {}
            repeated = self.q_ensemble.repeated_values(obs[:n], acts[:n], **kwargs).mean(0)
            chosen = torch.where(need, repeated - value_phy >= self._epsilon(value_phy), chosen)
        return chosen, (~chosen).long()

    def streak_state(self) -> list | None:
        """The veto count of the takeover in progress (``veto_patience`` > 1), as JSON data: None (no count yet: the
        next ``select`` starts one) or the nested list of the count tensor (``(*B,)``, int64)."""
        return None if self._veto_streak is None else self._veto_streak.tolist()

    def load_streak_state(self, state: list | int | None) -> None:
        """Restore :meth:`streak_state` (None: the fresh state)."""
        self._veto_streak = None if state is None else torch.as_tensor(state, dtype=torch.long)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, mentor, phy = (tensordict.get(k) for k in self.in_keys)
        hybrid, chosen = self.select(obs, mentor, phy)
        tensordict.set(self.out_keys[0], hybrid)
        tensordict.set(self.out_keys[1], chosen)
        return tensordict
