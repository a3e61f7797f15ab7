"""The driving world as a TorchRL env.

``make_env(config)`` returns a ``TransformedEnv`` over :class:`DrivingTorchEnv`.
TensorDict keys (batch shape ``[]`` for one env, ``[N]`` inside ``ParallelEnv``):

- ``observation``: float32 ``(250,)`` (layout in :mod:`pe_rlhf.envs.observation`);
- ``action``: float32 ``(2,)``, ``[steering, throttle]`` in [-1, 1];
- under ``next``: ``reward`` float32 ``(1,)``, ``done``/``terminated``/``truncated`` bool ``(1,)``,
  and the step info: ``cost``, ``route_completion``, ``travel_distance`` [m], ``velocity``
  [km/h] float32 ``(1,)``; ``success``, ``crash_vehicle``, ``crash_object``, ``out_of_road``
  bool ``(1,)``; ``overtakes``, ``scene_seed`` int64 ``(1,)``; ``sim_error`` bool ``(1,)``: the
  simulator failed this step (raised, or returned NaN/inf), so the episode ended here as truncated
  (see :mod:`pe_rlhf.envs.driving_env`; a collector resets and goes on);
- with ``make_env(..., episode_stats=True)``: ``step_count`` int64 ``(1,)`` and
  ``episode_reward`` float32 ``(1,)`` (running sum, ``RewardSum``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium.utils import seeding as gym_seeding
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, RewardSum, StepCounter, TransformedEnv

from pe_rlhf.envs.config import DrivingConfig

FLOAT_INFO = ("cost", "route_completion", "travel_distance", "velocity")
BOOL_INFO = ("success", "crash_vehicle", "crash_object", "out_of_road")
INT_INFO = ("overtakes", "scene_seed")


def _info_spec() -> dict:
    specs = {k: Unbounded((1,), dtype=torch.float32) for k in FLOAT_INFO}
    specs.update({k: Unbounded((1,), dtype=torch.bool) for k in BOOL_INFO + ("sim_error",)})
    specs.update({k: Unbounded((1,), dtype=torch.int64) for k in INT_INFO})
    return specs


class DrivingTorchEnv(EnvBase):
    """``DrivingEnv`` as a TorchRL ``EnvBase``, written lean (no ``GymWrapper`` plumbing).

    The simulator step costs ~1-2 ms; a generic wrapper adds ~0.4 ms, so this class
    builds the output TensorDict directly. ``env.reset(scene_seed=k)`` (also through a
    ``TransformedEnv``) or a ``scene_seed`` entry in the reset TensorDict of the base env
    loads scene ``k``; otherwise a scene of the configured split is drawn with the env's
    RNG (``set_seed``).
    ``driving_env`` is the underlying gymnasium env (privileged simulator access).
    """

    def __init__(self, config: DrivingConfig | dict | None = None, render_mode: str | None = None):
        super().__init__(device="cpu", batch_size=torch.Size([]))
        from pe_rlhf.envs.driving_env import DrivingEnv

        self.driving_env = DrivingEnv(config, render_mode=render_mode)
        n = self.driving_env.observation_space.shape[0]
        self.observation_spec = Composite(
            observation=Bounded(-1.0, 1.0, (n,), dtype=torch.float32), **_info_spec(), shape=[]
        )
        self.action_spec = Bounded(-1.0, 1.0, (2,), dtype=torch.float32)
        self.reward_spec = Unbounded((1,), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, (1,), dtype=torch.bool),
            terminated=Categorical(2, (1,), dtype=torch.bool),
            truncated=Categorical(2, (1,), dtype=torch.bool),
            shape=[],
        )

    @staticmethod
    def _output(obs: np.ndarray, info: dict, reward: float = 0.0, terminated: bool = False,
                truncated: bool = False) -> TensorDictBase:
        """The step (or reset) TensorDict: one tensor per dtype, unbound into ``(1,)`` views (a tensor
        per key costs ~25 us a step more, ~1.5% of a simulator step)."""
        floats = torch.tensor([info[k] for k in FLOAT_INFO] + [reward], dtype=torch.float32).unsqueeze(-1)
        bools = torch.tensor([info[k] for k in BOOL_INFO] + [info.get("sim_error", False), terminated, truncated,
                                                             terminated or truncated], dtype=torch.bool).unsqueeze(-1)
        ints = torch.tensor([info[k] for k in INT_INFO], dtype=torch.int64).unsqueeze(-1)
        out = {"observation": torch.from_numpy(obs)}
        out.update(zip(FLOAT_INFO + ("reward",), floats.unbind(0)))
        out.update(zip(BOOL_INFO + ("sim_error", "terminated", "truncated", "done"), bools.unbind(0)))
        out.update(zip(INT_INFO, ints.unbind(0)))
        return TensorDict._new_unsafe(out, batch_size=torch.Size([]))  # keys and shapes are ours: no checks

    def _reset(self, tensordict: TensorDictBase | None = None, scene_seed: int | None = None,
               **kwargs) -> TensorDictBase:
        if scene_seed is None and tensordict is not None and "scene_seed" in tensordict.keys():
            scene_seed = int(tensordict.get("scene_seed").reshape(-1)[0])
        options = None if scene_seed is None else {"scene_seed": int(scene_seed)}
        obs, info = self.driving_env.reset(options=options)
        out = self._output(obs, info)
        del out["reward"]  # a reset has no reward
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy()
        obs, reward, terminated, truncated, info = self.driving_env.step(action)
        return self._output(obs, info, float(reward), bool(terminated), bool(truncated))

    def _set_seed(self, seed: int | None) -> None:
        self.driving_env._np_random, _ = gym_seeding.np_random(seed)

    def render(self):
        return self.driving_env.render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        self.driving_env.close()
        super().close(raise_if_closed=raise_if_closed)


def make_base_env(config: DrivingConfig | dict | None = None, render_mode: str | None = None) -> DrivingTorchEnv:
    """The untransformed TorchRL env; picklable by ``functools.partial`` for ``ParallelEnv`` workers."""
    return DrivingTorchEnv(config, render_mode)


class DrivingTransformedEnv(TransformedEnv):
    """``TransformedEnv`` that forwards a ``scene_seed`` entry of the reset TensorDict.

    (TorchRL's ``TransformedEnv._reset`` keeps only reset and state keys of its input,
    which would drop the requested scene; ``ParallelEnv`` resets go through this path.)
    """

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        # With no transform (make_env's default) there is nothing to invert or apply, and the base
        # env writes every done key itself: skip TransformedEnv's clone-and-complete (~30 us a step).
        transform = self.transform
        if isinstance(transform, Compose) and not len(transform) and "_step" not in tensordict.keys() \
                and "next" not in tensordict.keys():
            return self.base_env._step(tensordict)
        return super()._step(tensordict)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs):
        if tensordict is None or "scene_seed" not in tensordict.keys():
            return super()._reset(tensordict, **kwargs)
        td = self.transform._reset_env_preprocess(
            tensordict.select(*self.reset_keys, "scene_seed", strict=False)
        )
        out = self.base_env._reset(td, **kwargs)
        self.base_env._complete_done(self.base_env.full_done_spec, out)
        return self.transform._reset(td, out)


def make_env(
    config: DrivingConfig | dict | None = None, render_mode: str | None = None, episode_stats: bool = False
) -> TransformedEnv:
    """The TorchRL driving env, a ``TransformedEnv`` ready for more transforms (e.g. interventions).

    With ``episode_stats``, adds ``StepCounter`` (``step_count``) and ``RewardSum``
    (``episode_reward``); off by default because each costs ~5% of a step here.
    """
    transforms = [StepCounter(), RewardSum(in_keys=["reward"], out_keys=["episode_reward"])] if episode_stats else []
    return DrivingTransformedEnv(make_base_env(config, render_mode), Compose(*transforms))


def unwrap(env) -> Any:
    """The ``DrivingEnv`` inside a (transformed) TorchRL env, or ``env`` itself if it is one."""
    base = env
    while hasattr(base, "base_env"):
        base = base.base_env
    return getattr(base, "driving_env", base)


__all__ = ["DrivingTorchEnv", "DrivingTransformedEnv", "make_base_env", "make_env", "unwrap"]
