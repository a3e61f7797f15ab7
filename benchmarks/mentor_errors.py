"""How often a simulated mentor's own actions are wrong: a preset driving alone on TRAIN scenes at chosen fatigue.

For each ``error_rate`` and fatigue multiplier: success and episodes with a violation, mean speed, the share of
its steps inside a wrong manoeuvre (``SimulatedMentor.manoeuvre`` not None: a steering pulse, needless braking,
throttle, or a danger seek) and the share of hard-braking steps (throttle <= -0.6). What a learner imitating its
labels would see; calibrated here on train scenes only.

    python benchmarks/mentor_errors.py --preset amateur --error-rates 0.06 0.01 --fatigue 1 3 --scenes 0-9 [--json OUT]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.envs.splits import parse_seeds
from pe_rlhf.evaluation.evaluate import run_episode
from pe_rlhf.mentors.simulated import SimulatedMentor, preset


class CountingDriver:
    """The mentor driving alone (a ``Policy``), counting the steps inside a wrong manoeuvre and hard braking."""

    def __init__(self, mentor: SimulatedMentor):
        self.mentor, self.steps, self.in_error, self.hard_brake = mentor, 0, 0, 0

    def reset(self) -> None:
        pass

    def __call__(self, obs, env) -> np.ndarray:
        action = self.mentor.act(env)
        self.steps += 1
        self.in_error += self.mentor.manoeuvre is not None
        self.hard_brake += bool(action[1] <= -0.6)
        return action


def measure(name: str, error_rate: float | None, fatigue: float, scenes, seed: int = 0) -> dict:
    profile = preset(name) if error_rate is None else dataclasses.replace(preset(name), error_rate=error_rate)
    mentor = SimulatedMentor(profile, seed=seed, name=name)
    if profile.fatigue_rate > 0:  # the controlled steps that give this fatigue
        mentor.controlled_steps = int(round((min(fatigue, profile.max_fatigue) - 1.0) * 1000 / profile.fatigue_rate))
    driver = CountingDriver(mentor)
    env = make_gym_env(DrivingConfig.from_dict({"lane_features": True, "split": "train"}))
    try:
        episodes = [run_episode(env, driver, s) for s in scenes]
    finally:
        env.close()
    return {"preset": name, "error_rate": profile.error_rate, "fatigue": mentor.fatigue,
            "success": float(np.mean([e.success for e in episodes])),
            "violation_episodes": float(np.mean([e.safety_violation > 0 for e in episodes])),
            "velocity_kmh": float(np.mean([e.travel_velocity for e in episodes])),
            "error_step_share": driver.in_error / driver.steps, "hard_brake_share": driver.hard_brake / driver.steps,
            "steps": driver.steps}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="amateur")
    parser.add_argument("--error-rates", type=float, nargs="*", default=[], help="default: the preset's own")
    parser.add_argument("--fatigue", type=float, nargs="+", default=[1.0, 3.0])
    parser.add_argument("--scenes", default="0-9", help="train scenes 'A-B'")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    scenes = parse_seeds(args.scenes)
    if any(s >= 1000 for s in scenes):
        parser.error("--scenes: train scenes only (0-49)")
    rows = []
    for rate in args.error_rates or [None]:
        for fatigue in args.fatigue:
            rows.append(measure(args.preset, rate, fatigue, scenes))
            r = rows[-1]
            print(f"{r['preset']} error_rate {r['error_rate']} fatigue x{r['fatigue']:.1f}: "
                  f"success {r['success']:.2f}, "
                  f"violation episodes {r['violation_episodes']:.2f}, {r['velocity_kmh']:.1f} km/h, steps in a wrong "
                  f"manoeuvre {r['error_step_share']:.3f}, hard braking {r['hard_brake_share']:.3f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return rows


if __name__ == "__main__":
    main()
