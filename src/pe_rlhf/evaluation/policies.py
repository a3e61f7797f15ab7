"""Policies that evaluation can drive: a small protocol, adapters, and a name registry.

A policy is any object with ``reset()`` (called before every episode) and
``__call__(obs, env) -> action``: ``obs`` is the float32 ``(250,)`` observation,
``env`` the :class:`~pe_rlhf.envs.driving_env.DrivingEnv` (privileged policies read
the simulator from it), and the action a float32 ``(2,)`` ``[steering, throttle]``
in ``[-1, 1]``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol, runtime_checkable

import numpy as np

from pe_rlhf.physics.policy import IDMMobilPolicy, PhysicsConfig

if TYPE_CHECKING:
    import torch


@runtime_checkable
class Policy(Protocol):
    """What :func:`pe_rlhf.evaluation.evaluate` drives: ``reset()`` then ``policy(obs, env)``."""

    def reset(self) -> None: ...

    def __call__(self, obs: np.ndarray, env) -> np.ndarray: ...


class RandomPolicy:
    """Uniform actions in ``[-1, 1]^2`` from a seeded generator.

    In: ``seed`` (int). A fresh ``RandomPolicy(seed)`` replays the same action stream;
    ``reset()`` does not reseed, so consecutive episodes get different actions.
    """

    def __init__(self, seed: int = 0):
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)

    def reset(self) -> None:
        pass

    def __call__(self, obs: np.ndarray, env) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, size=2).astype(np.float32)


class PhysicsPolicyAdapter:
    """The IDM + MOBIL physics policy (privileged: reads ``env``'s simulator state).

    In: a :class:`~pe_rlhf.physics.policy.PhysicsConfig` (defaults: paper parameters,
    braking for static obstacles in its lane, never passing them). Out: float32 ``(2,)`` actions; ``obs`` is ignored.
    """

    def __init__(self, config: PhysicsConfig | None = None):
        self.policy = IDMMobilPolicy(config or PhysicsConfig())

    def reset(self) -> None:
        self.policy.reset()

    def __call__(self, obs: np.ndarray, env) -> np.ndarray:
        return np.asarray(self.policy(env), dtype=np.float32).reshape(2)


class TorchRLPolicyAdapter:
    """Any tensordict module (``ProbabilisticActor``, ``TensorDictModule``, ...) as a policy.

    Reads ``in_key`` (the observation, float32 ``(250,)``, unbatched) and returns
    ``out_key`` as float32 numpy ``(2,)``, run under ``torch.no_grad()`` with the
    deterministic exploration type (the distribution's mode/mean, not a sample).
    torch/torchrl are imported on first use, so the CLI starts fast without them.
    """

    def __init__(self, module: Callable[[Any], Any], in_key: str = "observation",
                 out_key: str = "action"):
        self.module = module
        self.in_key = in_key
        self.out_key = out_key

    def reset(self) -> None:
        pass

    def _device(self) -> torch.device:
        import torch

        params = getattr(self.module, "parameters", None)
        first = next(iter(params()), None) if callable(params) else None
        return first.device if first is not None else torch.device("cpu")

    def __call__(self, obs: np.ndarray, env) -> np.ndarray:
        import torch
        from tensordict import TensorDict
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        x = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self._device())
        td = TensorDict({self.in_key: x}, batch_size=[])
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            out = self.module(td)
        return out.get(self.out_key).detach().cpu().numpy().astype(np.float32).reshape(2)


PolicyFactory = Callable[[int], Policy]

POLICY_FACTORIES: dict[str, PolicyFactory] = {
    "idm-mobil": lambda seed: PhysicsPolicyAdapter(PhysicsConfig()),  # brakes for obstacles (the default)
    "idm-mobil-stop": lambda seed: PhysicsPolicyAdapter(PhysicsConfig(stop_for_obstacles=True)),  # = idm-mobil
    "idm-mobil-blind": lambda seed: PhysicsPolicyAdapter(PhysicsConfig(stop_for_obstacles=False)),
    "idm-mobil-oracle": lambda seed: PhysicsPolicyAdapter(PhysicsConfig(see_obstacles=True)),
    "random": lambda seed: RandomPolicy(seed),
}


def register_policy(name: str, factory: PolicyFactory, overwrite: bool = False) -> None:
    """Make ``make_policy(name, seed)`` call ``factory(seed)``; re-registering needs ``overwrite``."""
    if name in POLICY_FACTORIES and not overwrite:
        raise ValueError(f"policy {name!r} is already registered (pass overwrite=True to replace it)")
    POLICY_FACTORIES[name] = factory


def make_policy(name: str, seed: int = 0) -> Policy:
    """A fresh policy from the registry. In: a registered name and a seed; unknown names raise ValueError."""
    if name not in POLICY_FACTORIES:
        raise ValueError(f"unknown policy {name!r}; allowed: {sorted(POLICY_FACTORIES)}")
    return POLICY_FACTORIES[name](int(seed))
