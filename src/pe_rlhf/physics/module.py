"""The physics policy as a tensordict module acting in a TorchRL driving env."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from pe_rlhf.envs.torchrl_env import unwrap
from pe_rlhf.physics.policy import IDMMobilPolicy, PhysicsConfig


class PhysicsPolicyModule(TensorDictModuleBase):
    """Writes the IDM-MOBIL action for the env's current state.

    Reads: nothing from the TensorDict (the physics policy reads the simulator's
    state, which is privileged); ``observation`` is declared so TorchRL's plumbing
    sees a normal policy. Writes: ``action`` float32 ``(2,)`` ``[steering, throttle]``.
    Works with ``env.rollout(policy=module)`` and a single-process ``Collector``
    on the same env object (it needs the simulator in this process).
    """

    def __init__(self, env, config: PhysicsConfig | None = None, action_key: str = "action"):
        super().__init__()
        self.in_keys = ["observation"]
        self.out_keys = [action_key]
        self.driving_env = unwrap(env)
        self.policy = IDMMobilPolicy(config)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_size != torch.Size([]):
            raise ValueError(
                f"PhysicsPolicyModule drives one simulator; got batch size {tuple(tensordict.batch_size)}"
            )
        action = torch.as_tensor(self.policy(self.driving_env))
        tensordict.set(self.out_keys[0], action)
        return tensordict
