"""``examples/sb3_sac_intervention.py`` learns: Stable-Baselines3 SAC through ``InterventionWrapper`` on Pendulum-v1."""

from __future__ import annotations

import numpy as np
import pytest
from _scripts import load_script

pytest.importorskip("stable_baselines3")


def test_sb3_sac_through_the_wrapper_beats_random_torques(one_thread):
    example = load_script("examples/sb3_sac_intervention.py")
    model, rates = example.train(total_steps=5000, seed=0)
    assert len(rates) == 25 and all(0.0 <= r <= 1.0 for r in rates)  # 200-step episodes
    assert max(rates) > 0.1, rates  # the mentor did take over
    assert np.mean(rates[-4:]) < 0.5 * max(rates), rates  # and takes over less once the agent balances
    trained = example.evaluate(lambda obs: model.predict(obs, deterministic=True)[0])  # alone, 10 episodes
    random = example.evaluate()  # uniform torques, the same 10 initial states
    assert trained > random + 400.0, (trained, random)
