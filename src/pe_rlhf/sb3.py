"""Stable-Baselines3 learners that store the executed action of a takeover (optional: ``pip install
'pe-rlhf[sb3]'``).

SB3 stores the action its policy sampled; under :class:`~pe_rlhf.wrappers.InterventionWrapper` a takeover
executed another one (``info["teleop_action"]``, with ``info["is_intervention"]``), and the simulator moved by
that one. :class:`StoreExecutedAction` stores it instead, so ``(s, a_exec, r, s')`` is the transition that
happened (as HIL-SERL does). It mixes into any off-policy SB3 algorithm; :class:`InterventionSAC` and
:class:`InterventionTD3` are the two ready-made ones::

    model = InterventionSAC("MlpPolicy", InterventionWrapper(gym.make("Pendulum-v1"), mentor)).learn(5000)

Plain SAC/TD3 learn from the env reward: they need a mentor that steps in rarely (``docs/wrappers.md``); the
reward-free takeover losses of HACO / PE-RLHF are :class:`~pe_rlhf.objectives.PERLHFLoss`.
"""

from __future__ import annotations

import numpy as np

try:
    from stable_baselines3 import SAC, TD3
except ImportError as e:  # one line naming the fix, not SB3's traceback
    raise ImportError(f"pe_rlhf.sb3 needs Stable-Baselines3: pip install 'pe-rlhf[sb3]' ({e})") from e


class StoreExecutedAction:
    """Mixin (before the SB3 algorithm): each env whose ``info["is_intervention"]`` is true stores
    ``info["teleop_action"]`` (in the env's action units, scaled to the policy's ``[-1, 1]`` as SB3 stores its
    own) as the transition's action; the other envs keep the policy's."""

    def _store_transition(self, replay_buffer, buffer_action: np.ndarray, new_obs, reward, dones, infos) -> None:
        buffer_action = buffer_action.copy()  # SB3 reuses the array as the next step's action
        for i, info in enumerate(infos):
            if info.get("is_intervention"):
                buffer_action[i] = self.policy.scale_action(np.asarray(info["teleop_action"]))
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)


class InterventionSAC(StoreExecutedAction, SAC):
    """SB3's ``SAC`` storing a takeover's executed action (:class:`StoreExecutedAction`); SAC's arguments."""


class InterventionTD3(StoreExecutedAction, TD3):
    """SB3's ``TD3`` storing a takeover's executed action (:class:`StoreExecutedAction`); TD3's arguments."""


__all__ = ["InterventionSAC", "InterventionTD3", "StoreExecutedAction"]
