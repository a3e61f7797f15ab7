"""PE-RLHF's pieces in a plain TorchRL pipeline on Pendulum-v1 (no reward reaches the agent).

``InterventionTransform`` (scripted mentor + physics controller + ``HybridActionSelector``) wraps
``GymEnv("Pendulum-v1")``; a ``Collector`` fills a ``TensorDictReplayBuffer``; ``PERLHFLoss`` + Adam +
``SoftUpdate`` train a SAC-style actor. The mentor (bang-bang energy pumping, PD near the top) takes over
when the pole is far from upright or falling and the agent pushes the other way. The physics controller
(energy shaping + feedback-linearised PD from the equation of motion) is the alternative the selector may
execute instead; its Q-ensemble is fitted with the env reward on the warm-up data (the mentor drives).
Run ``python examples/pendulum_intervention.py``: the takeover rate falls as the agent learns.
"""

import math

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import ActionScaling, Compose, GymEnv, TransformedEnv
from torchrl.objectives import SoftUpdate

from pe_rlhf.mentors import Mentor, MentorDecision
from pe_rlhf.modules.networks import make_actor, make_qvalue
from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.objectives.perlhf import PERLHFLoss
from pe_rlhf.transforms import HybridActionSelector, InterventionTransform

WARMUP, FRAMES_PER_BATCH, UPDATES_PER_BATCH, HIDDEN = 400, 200, 100, (64, 64)


def controller(th, thd, physics=False):
    """Normalised torque (batched tensors). ``th``: angle from upright; energy is 0 upright at rest."""
    th = (th + math.pi) % (2 * math.pi) - math.pi
    energy, way = 0.5 * thd**2 + 15.0 * (torch.cos(th) - 1.0), torch.where(thd >= 0, 1.0, -1.0)
    if physics:  # energy shaping + feedback-linearised PD
        swing, top = -0.3 * energy * way, (-15.0 * torch.sin(th) - 8.0 * th - 3.0 * thd) / 6.0
    else:  # the mentor: bang-bang pumping + PD
        swing, top = -torch.sign(energy) * way * (energy.abs() > 1.0), -(10.0 * th + 2.0 * thd) / 2.0
    return torch.where(torch.cos(th) > 0.85, top, swing).clamp(-1.0, 1.0)


def on_env(env, physics=False):  # the transform hands GymEnv's ``_env.unwrapped`` (PendulumEnv) over
    return controller(*torch.as_tensor(env.state, dtype=torch.float32), physics).reshape(1).numpy()


class SwingUpMentor(Mentor):
    """Takes over when the pole is far from upright or falling and the agent pushes the other way (by > 0.5).

    Judging the direction, not the exact torque, lets the agent stop takeovers by learning either executed
    action, the mentor's or the physics controller's (they push the same way where it matters)."""

    def act(self, env):
        return on_env(env)

    def decide(self, env, agent_action):
        own, (th, thd) = self.act(env), env.state
        th = (th + math.pi) % (2 * math.pi) - math.pi
        risky = math.cos(th) < 0.95 or th * thd > 0  # far from upright, or falling away from it
        opposed = agent_action[0] * own[0] < 0 and abs(agent_action[0] - own[0]) > 0.5
        return MentorDecision(bool(risky and opposed), own)


def fit_ensemble(ensemble, buffer, steps=500, gamma=0.99):
    """The paper's estimator loss ``(0.1 r + gamma mean_k Q_k(s', a') - mean_k Q_k(s, a))^2``,
    ``a' = mentor(s') + N(0, 0.1)``, on the warm-up data (reward scaled to ~[-1.6, 0] per step)."""
    optim = torch.optim.Adam(ensemble.parameters(), lr=1e-3)
    for _ in range(steps):
        td = buffer.sample()
        obs, nxt = td["observation"], td["next", "observation"]
        with torch.no_grad():
            a_next = controller(torch.atan2(nxt[:, 1], nxt[:, 0]), nxt[:, 2])[:, None]
            a_next = (a_next + 0.1 * torch.randn_like(a_next)).clamp(-1, 1)
            alive = 1.0 - td["next", "terminated"].squeeze(-1).float()
            y = 0.1 * td["next", "reward"].squeeze(-1) + gamma * alive * ensemble.values(nxt, a_next).mean(0)
        loss = (ensemble.values(obs, td["next", "behavior_action"]).mean(0) - y).pow(2).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()


def main(total_frames=2800, seed=0, verbose=True):
    """Train; returns the takeover rate of each batch after the warm-up (during it the mentor always drives)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny networks: one thread is fastest and does not fight other processes
    try:
        torch.manual_seed(seed)
        ensemble = QEnsemble(3, 1, num_members=3, hidden=HIDDEN)
        intervention = InterventionTransform(SwingUpMentor(), HybridActionSelector(ensemble, epsilon_select=0.0),
                                             physics=lambda env: on_env(env, physics=True), warmup_steps=WARMUP)
        env = TransformedEnv(GymEnv("Pendulum-v1"), Compose(ActionScaling(), intervention))  # agent acts in [-1, 1]
        env.set_seed(seed)
        actor = make_actor(3, 1, HIDDEN)
        loss = PERLHFLoss(actor, make_qvalue(3, 1, HIDDEN), make_qvalue(3, 1, HIDDEN), gap_coef=1.0, action_dim=1)
        optim, target_update = torch.optim.Adam(loss.parameters(), lr=1e-3), SoftUpdate(loss, tau=0.005)
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(total_frames), batch_size=256)
        collector = Collector(env, actor, frames_per_batch=FRAMES_PER_BATCH, total_frames=total_frames,
                              auto_register_policy_transforms=False)
        rates, frames = [], 0
        for batch in collector:
            buffer.extend(batch.reshape(-1))
            frames += batch.numel()
            if frames == WARMUP:
                fit_ensemble(ensemble, buffer)  # then frozen: the selector's judge
            elif frames > WARMUP:
                taken = batch["next", "intervention"]
                rates.append(taken.float().mean().item())
                if verbose:
                    chosen = batch["next", "mentor_selected"][taken].float().mean().item() if taken.any() else 0.0
                    print(f"frames {frames:5d}  takeover rate {rates[-1]:.3f}  mentor chosen {chosen:.2f}")
            for _ in range(UPDATES_PER_BATCH):
                out = loss(buffer.sample())
                total = out["loss_qvalue"] + out["loss_intervention_qvalue"] + out["loss_actor"] + out["loss_alpha"]
                optim.zero_grad()
                total.backward()
                optim.step()
                target_update.step()
        collector.shutdown()
        return rates
    finally:
        torch.set_num_threads(threads)


if __name__ == "__main__":
    main()
