"""``examples/pendulum_intervention.py`` learns: the mentor's takeover rate falls over a short training run."""

from __future__ import annotations

import numpy as np
from _scripts import load_script


def _load_example():
    return load_script("examples/pendulum_intervention.py")


def test_takeover_rate_falls_over_training():
    example = _load_example()
    rates = example.main(total_frames=2000, seed=0, verbose=False)
    # 2000 frames = 2 warm-up batches (not returned: the mentor drives every step) + 8 batches of 200.
    assert len(rates) == 8 and all(0.0 <= r <= 1.0 for r in rates)
    quarter = len(rates) // 4
    first, last = float(np.mean(rates[:quarter])), float(np.mean(rates[-quarter:]))
    assert first > 0.2, rates  # a fresh agent gets taken over often
    assert last < 0.7 * first, rates
