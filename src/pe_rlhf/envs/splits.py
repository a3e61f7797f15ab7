"""Fixed scene-seed splits: 50 training scenes, 50 validation scenes and 50 test scenes, pairwise disjoint.

Agents train on ``train``; ``validation`` holds scenes no agent trains on and no final table reports, for choosing
settings on scenes the agent has not seen; ``test`` is for final evaluations only.
"""

from __future__ import annotations

TRAIN_SEEDS = tuple(range(0, 50))
VALIDATION_SEEDS = tuple(range(500, 550))
TEST_SEEDS = tuple(range(1000, 1050))
SPLITS = {"train": TRAIN_SEEDS, "validation": VALIDATION_SEEDS, "test": TEST_SEEDS}


def scene_seeds(split: str) -> tuple[int, ...]:
    """The scene seeds of ``split`` ('train', 'validation' or 'test')."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; allowed: {sorted(SPLITS)}")
    return SPLITS[split]


def parse_seeds(text: str) -> tuple[int, ...]:
    """Parse ``'2000-2049'`` (inclusive range) or ``'3,5,8'`` into seeds."""
    try:
        if "-" in text.strip().lstrip("-"):
            lo, hi = text.split("-", 1)
            lo_i, hi_i = int(lo), int(hi)
            if hi_i < lo_i:
                raise ValueError
            return tuple(range(lo_i, hi_i + 1))
        return tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise ValueError(f"bad seeds {text!r}: use 'A-B' (inclusive) or a comma list 'a,b,c'") from None
