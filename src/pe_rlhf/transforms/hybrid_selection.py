"""``HybridSelectionTransform``: PE-RLHF's hybrid action selection as a TorchRL transform of its own.

On the way to the simulator (the inverse path), wherever a step is marked ``intervention``, the transform
executes ``a_hybrid``: the mentor's proposal if the selector values it enough above physics', else physics'
(:class:`~pe_rlhf.transforms.HybridActionSelector`, whose value source and ``epsilon_select`` it uses). Steps
not marked keep the action they carry. The proposals may come from any source that writes them into the
tensordict before the simulator moves: :class:`~pe_rlhf.transforms.InterventionTransform` given ``physics``
and no selector, a policy-side module, or a transform fed from another library's intervention info.

TorchRL runs inverse transforms from the last in a ``Compose`` to the first, so the selection, which follows
its source in the action's path, sits *before* the source (nearer the simulator)::

    env = TransformedEnv(base, Compose(HybridSelectionTransform(selector), source))

Reads on the inverse path (``in_keys``, renamable, in this order; batch dims ``*B`` as the env's):

=========================  ===========================================================
``action`` (*B, A)         the action on its way to the simulator; replaced where judged
``observation`` (*B, O)    what the selector's value source reads
``mentor_action`` (*B, A)  the mentor's proposal
``physics_action`` (*B, A) the physics proposal
``intervention`` (*B, 1)   bool: this step is a takeover to judge
=========================  ===========================================================

Writes ``mentor_selected`` (*B, 1) bool on the inverse path (for transforms nearer the simulator and the
source's ``_step``), and under ``next`` (``out_keys``, in this order): ``behavior_action`` (*B, A) float32, the
action executed, and ``mentor_selected`` (*B, 1) bool, the mentor's proposal was executed in a judged step.

``switch_margin`` (the selector's) makes a choice sticky over consecutive judged steps of the same env.
``veto_patience`` (the selector's) counts consecutive vetoes per batch row: a row's count starts from 0 where its
takeover starts (its previous step was not judged, or the row was reset) and goes on over its consecutive judged
steps, whatever the other rows do; the transform keeps the counts (``(*B,)`` int64), not the selector. A value
source that forecasts from the simulator (``needs_env``) serves an unbatched env only.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from pe_rlhf.transforms.intervention import simulator_of
from pe_rlhf.transforms.keys import (BEHAVIOR_ACTION, INTERVENTION, MENTOR_ACTION, MENTOR_SELECTED,
                                     PHYSICS_ACTION)
from pe_rlhf.transforms.selector import HybridActionSelector

IN_KEYS = ("action", "observation", MENTOR_ACTION, PHYSICS_ACTION, INTERVENTION)
SELECTION_OUT_KEYS = (BEHAVIOR_ACTION, MENTOR_SELECTED)


class HybridSelectionTransform(Transform):
    """The hybrid action selection on the inverse path of a ``TransformedEnv`` (see the module docstring).

    Args:
        selector: the :class:`~pe_rlhf.transforms.HybridActionSelector` that chooses (its value source,
            ``epsilon_select``, ``variance_threshold``, ``switch_margin``, ``veto_patience`` and
            ``imminent_failure``; the veto counts are the transform's, one per batch row).
        in_keys: ``[action, observation, mentor_action, physics_action, intervention]``.
        out_keys: ``[behavior_action, mentor_selected]``.
    """

    def __init__(self, selector: HybridActionSelector, *, in_keys=IN_KEYS, out_keys=SELECTION_OUT_KEYS):
        in_keys, out_keys = list(in_keys), list(out_keys)
        if len(in_keys) != len(IN_KEYS) or len(out_keys) != len(SELECTION_OUT_KEYS):
            raise ValueError(f"HybridSelectionTransform: in_keys are {list(IN_KEYS)} (got {in_keys}); out_keys are "
                             f"{list(SELECTION_OUT_KEYS)} (got {out_keys})")
        if not isinstance(selector, HybridActionSelector):
            raise TypeError(f"HybridSelectionTransform needs a HybridActionSelector, got {type(selector).__name__}")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.selector = selector
        self.action_key, self.observation_key, self.mentor_key, self.physics_key, self.intervention_key = in_keys
        self.behavior_key, self.selected_key = out_keys
        self._previous: torch.Tensor | None = None  # (*B, 1) the last judged step's choice (mentor?)
        self._was_judged: torch.Tensor | None = None  # (*B, 1) the last step was judged
        self._veto_streak: torch.Tensor | None = None  # (N,) each row's consecutive vetoes in its takeover

    def veto_counts(self) -> torch.Tensor:
        """Each batch row's count of consecutive vetoes in its takeover so far, int64 ``(*B,)`` (zeros where no
        takeover is going on: the last step was not judged, or the row was reset)."""
        shape = () if self._was_judged is None else self._was_judged.shape[:-1]
        if self._veto_streak is None or self._was_judged is None:
            return torch.zeros(shape, dtype=torch.long)
        return torch.where(self._was_judged.reshape(-1), self._veto_streak, 0).reshape(shape)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # No takeover carries over an episode's start: the rows reset (all, without a ``_reset`` mask) are unjudged.
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is None or self._was_judged is None or reset.numel() != self._was_judged.numel():
            self._previous = self._was_judged = torch.zeros((*tensordict_reset.batch_size, 1), dtype=torch.bool)
            self._veto_streak = None
        else:
            self._was_judged = self._was_judged & ~reset.reshape(self._was_judged.shape).to(torch.bool)
        for key, spec in self.transform_observation_spec(Composite(shape=tensordict_reset.batch_size)).items():
            tensordict_reset.set(key, spec.zero())
        return tensordict_reset

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # the choice is made on the way to the simulator

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        missing = [str(k) for k in (self.mentor_key, self.physics_key, self.intervention_key)
                   if tensordict.get(k, None) is None]
        if missing:
            raise KeyError(f"HybridSelectionTransform: no {', '.join(missing)} in the tensordict on its way to the "
                           "simulator; the source that writes them must come after this transform in the Compose "
                           "(TorchRL runs inverse transforms last to first)")
        action = tensordict.get(self.action_key)
        judged = tensordict.get(self.intervention_key).to(torch.bool).reshape(*action.shape[:-1], 1)
        chosen = torch.zeros_like(judged)
        if judged.any():
            hybrid, chosen = self._choose(tensordict, action.shape)
            action = torch.where(judged, hybrid.to(action.dtype), action)
            chosen = chosen & judged
            tensordict.set(self.action_key, action)
        tensordict.set(self.selected_key, chosen)
        self._previous, self._was_judged = chosen, judged
        return tensordict

    def _choose(self, tensordict: TensorDictBase, action_shape) -> tuple[torch.Tensor, torch.Tensor]:
        observation = tensordict.get(self.observation_key)
        mentor = tensordict.get(self.mentor_key).to(torch.float32)
        physics = tensordict.get(self.physics_key).to(torch.float32)
        kwargs = {}
        if getattr(self.selector.q_ensemble, "needs_env", False):
            if len(action_shape) > 1:
                raise ValueError(f"HybridSelectionTransform: {type(self.selector.q_ensemble).__name__} forecasts "
                                 "from one simulator; this env is batched")
            kwargs["env"] = simulator_of(self.parent)
        streak = self.veto_counts().reshape(-1)  # 0 where a row's takeover starts at this step
        hybrid, chosen, new_streak = self.selector.select_counted(observation, mentor, physics, None, streak, **kwargs)
        sticky = self.selector.switch_margin is not None and self._was_judged is not None
        if sticky and self._was_judged.any():  # consecutive judged steps: the choice the previous one made
            hybrid_held, chosen_held, _ = self.selector.select_counted(observation, mentor, physics, self._previous,
                                                                       streak, **kwargs)
            hold = self._was_judged.reshape(chosen.shape)
            hybrid = torch.where(hold, hybrid_held, hybrid)
            chosen = torch.where(hold, chosen_held, chosen)
        self._veto_streak = new_streak.reshape(-1)  # rows not judged now restart at their next judged step
        return hybrid, chosen.reshape(*action_shape[:-1], 1)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # ``tensordict`` is what the simulator received: its action is the one executed.
        next_tensordict.set(self.behavior_key, tensordict.get(self.action_key).to(torch.float32))
        next_tensordict.set(self.selected_key, tensordict.get(self.selected_key))
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        if self.parent is not None:
            action_shape = self.parent.full_action_spec[self.action_key].shape
            batch = tuple(self.parent.batch_size)
        else:
            action_shape, batch = (*observation_spec.shape, 2), tuple(observation_spec.shape)
        observation_spec[self.behavior_key] = Unbounded(action_shape, dtype=torch.float32)
        observation_spec[self.selected_key] = Unbounded((*batch, 1), dtype=torch.bool)
        return observation_spec


__all__ = ["HybridSelectionTransform", "IN_KEYS", "SELECTION_OUT_KEYS"]
