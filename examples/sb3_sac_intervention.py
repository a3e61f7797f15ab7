"""Stable-Baselines3 SAC on ``Pendulum-v1`` through ``InterventionWrapper``: a scripted mentor catches the pole.

The mentor (energy pumping far from upright, PD near it; torques in N m) takes over near the top
(``cos(theta) > UPRIGHT``) whenever the agent's torque differs from its own by more than ``TOLERANCE``.
The wrapper executes the mentor's torque then and says so in ``info`` (``is_intervention``,
``teleop_action``); :class:`pe_rlhf.sb3.InterventionSAC` stores that executed torque in its replay buffer instead of its own
proposal (the simulator moved by it: ``(s, a_exec, r, s')`` is the true transition, as HIL-SERL does). SAC
learns from the env reward; as the agent learns to balance, the takeovers fade.
Run ``python examples/sb3_sac_intervention.py`` (5000 steps): the trained agent, alone, swings the
pendulum up and holds it (mean return about -200 to -400, random torques about -1300).

Why only near the top: a mentor that vetoes the agent's actions everywhere (half the steps of a fresh agent)
leaves plain SAC blind to what those actions do; its critic then overvalues them and the agent alone does
worse than random (measured: -1100 to -1600 after 5000 steps). The takeover losses of HACO / PE-RLHF
(:class:`~pe_rlhf.objectives.PERLHFLoss`) exist for that; plain SAC needs a mentor that steps in rarely.
"""

import math

import gymnasium as gym
import numpy as np
import torch

from pe_rlhf.mentors import Mentor, MentorDecision
from pe_rlhf.sb3 import InterventionSAC
from pe_rlhf.wrappers import InterventionWrapper

TOLERANCE = 1.0  # [N m], of Pendulum's 2
UPRIGHT = 0.8  # cos(theta) above which the mentor watches
MAX_TORQUE = 2.0


class SwingUpMentor(Mentor):
    """Bang-bang energy pumping far from upright, PD near it; reads ``PendulumEnv.state`` (angle, rate).
    Takes over near the top when the agent's torque is more than ``TOLERANCE`` from its own."""

    name = "swing-up"

    def act(self, env) -> np.ndarray:
        th, thd = env.state
        th = (th + math.pi) % (2 * math.pi) - math.pi  # 0 upright
        energy = 0.5 * thd**2 + 15.0 * (math.cos(th) - 1.0)  # 0 upright at rest (g = 10, m = l = 1)
        if math.cos(th) > 0.85:
            torque = -(10.0 * th + 2.0 * thd)
        else:
            torque = -math.copysign(MAX_TORQUE, energy * thd) if abs(energy) > 1.0 else 0.0
        return np.array([np.clip(torque, -MAX_TORQUE, MAX_TORQUE)], dtype=np.float32)

    def decide(self, env, agent_action) -> MentorDecision:
        own = self.act(env)
        near_top = math.cos(env.state[0]) > UPRIGHT
        return MentorDecision(bool(near_top and np.abs(agent_action - own).max() > TOLERANCE), own)


def train(total_steps: int = 5000, seed: int = 0, verbose: int = 0):
    """``(model, takeover rate of each 200-step episode)`` after ``total_steps`` steps of SAC through the wrapper.

    Tuned to learn in few updates (a test runs it): 5-step returns, one update per 2 steps, lr 3e-3."""
    env = InterventionWrapper(gym.make("Pendulum-v1"), SwingUpMentor())
    model = InterventionSAC("MlpPolicy", env, learning_rate=3e-3, buffer_size=total_steps, learning_starts=200,
                            batch_size=128, gamma=0.98, n_steps=5, train_freq=2, ent_coef="auto_0.1",
                            policy_kwargs={"net_arch": [64, 64]}, seed=seed, verbose=verbose, device="cpu")
    rates, taken = [], []

    def record(locals_, globals_):  # SB3's callback-as-function: called after every env step
        taken.append(bool(locals_["infos"][0]["is_intervention"]))
        if locals_["dones"][0]:
            rates.append(float(np.mean(taken)))
            taken.clear()
        return True

    model.learn(total_timesteps=total_steps, callback=record)
    return model, rates


def evaluate(policy=None, episodes: int = 10, seed: int = 1000) -> float:
    """Mean return on plain ``Pendulum-v1`` (no mentor) of ``policy(obs) -> action``; None: uniform random torques."""
    env = gym.make("Pendulum-v1")
    env.action_space.seed(seed)
    returns = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done, total = False, 0.0
        while not done:
            action = env.action_space.sample() if policy is None else policy(obs)
            obs, reward, terminated, truncated, _ = env.step(action)
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def main(total_steps: int = 5000, seed: int = 0) -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small networks: one thread is fastest
    try:
        model, rates = train(total_steps, seed)
    finally:
        torch.set_num_threads(threads)
    print("takeover rate per episode:", " ".join(f"{r:.2f}" for r in rates))
    trained = evaluate(lambda obs: model.predict(obs, deterministic=True)[0])
    print(f"mean return, agent alone: {trained:.0f}  (random torques: {evaluate():.0f})")


if __name__ == "__main__":
    main()
