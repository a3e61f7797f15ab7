"""Manual smoke test: drive a test scene yourself as the mentor while the agent does nothing.

Run (needs a display): ``PYTHONPATH=src python examples/drive_as_mentor.py [scene_seed]``.
Hold Arrows/WASD (or move a gamepad stick / wheel) to take over; release to hand the car
back to the idle agent (zero action). P/Space pauses, Esc/Q or closing the window quits.
"""

import sys

import numpy as np

from pe_rlhf.envs import make_gym_env
from pe_rlhf.mentors.human import HumanMentor


def main(scene_seed: int = 1000) -> None:
    env = make_gym_env({"split": "test"})
    mentor = HumanMentor(fps=10)
    agent_action = np.zeros(2, dtype=np.float32)  # the "agent" just coasts
    env.reset(options={"scene_seed": scene_seed})
    mentor.reset(env)
    while not mentor.quit_requested:
        decision = mentor.decide(env, agent_action)
        action = decision.action if decision.takeover else agent_action
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            print(f"episode over: success={info['success']} takeovers={mentor.takeover_count}")
            env.reset(options={"scene_seed": scene_seed})
            mentor.reset(env)
    mentor.close()
    env.close()


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1000)
