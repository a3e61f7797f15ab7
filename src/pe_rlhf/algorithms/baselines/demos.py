"""The demonstrations the imitation baselines learn from: found, recorded when missing, loaded.

``data.path`` names a dataset directory of :mod:`pe_rlhf.mentors.recording` (what
``pe-rlhf demo record --mentor professional --split train --steps N --out DIR`` writes); null means
``<run folder>/demos``. :func:`ensure_demonstrations` records there (``data.mentor`` driving alone on the
training env's scenes) until it holds at least ``data.steps`` transitions, so a second run pointed at
the same path reuses them, and a larger ``data.steps`` extends them. :func:`load_transitions` returns
the first ``data.steps`` transitions, flat, with the keys the learners read:

- root: ``observation`` float32 ``(N, D)``, ``action`` float32 ``(N, 2)`` (the mentor's executed action);
- ``next``: ``observation``, ``reward``, ``cost`` ``(N, 1)`` float32, ``done``, ``terminated`` ``(N, 1)`` bool.

The dataset must have been recorded under the run's :class:`~pe_rlhf.envs.DrivingConfig` (checked:
a ValueError names each differing field).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf
from tensordict import TensorDictBase

from pe_rlhf.runtime.config import driving_config

DEMO_DIR = "demos"
DEMO_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "cost"),
             ("next", "done"), ("next", "terminated"))


def demonstration_dir(cfg, run_dir: str | Path | None) -> Path:
    """``data.path``, else ``<run_dir>/demos``."""
    if cfg.data.path is not None:
        return Path(str(cfg.data.path))
    if run_dir is None:
        raise ValueError("data.path is null and there is no run folder to record demonstrations into")
    return Path(run_dir) / DEMO_DIR


def _recorded_steps(directory: Path) -> int:
    from pe_rlhf.mentors.recording import read_manifest

    return sum(e["steps"] for e in read_manifest(directory)) if (directory / "metadata.json").is_file() else 0


def _mentor(name: str, seed: int):
    from pe_rlhf.runtime.world import build_mentor

    return build_mentor(OmegaConf.create({"seed": seed, "mentor": {"name": name, "kwargs": {}}}))


def ensure_demonstrations(cfg, directory: str | Path, progress: bool = True) -> dict:
    """Record ``data.mentor``'s driving into ``directory`` until it holds ``data.steps`` transitions
    (whole episodes; nothing when it already does); returns what was recorded (steps, seconds)."""
    from pe_rlhf.mentors.recording import DemonstrationRecorder, record

    directory = Path(directory)
    missing = int(cfg.data.steps) - _recorded_steps(directory)
    if missing <= 0:
        return {"steps": 0, "seconds": 0.0}
    mentor = _mentor(str(cfg.data.mentor), int(cfg.seed))
    name = getattr(mentor, "name", None) or str(cfg.data.mentor)
    with DemonstrationRecorder(directory, driving_config(cfg), name) as recorder:
        return record(mentor, recorder, missing, progress=progress)


def load_transitions(cfg, directory: str | Path) -> TensorDictBase:
    """The first ``data.steps`` transitions of the dataset in ``directory`` (module docstring's keys)."""
    from pe_rlhf.mentors.recording import load_demonstrations

    buffer = load_demonstrations(directory, driving_config(cfg))
    steps = int(cfg.data.steps)
    if len(buffer) < steps:
        raise ValueError(f"dataset {directory} holds {len(buffer)} transitions, data.steps asks for {steps}")
    return buffer.storage[:steps].select(*DEMO_KEYS).clone()


def demonstrations(cfg, run_dir: str | Path | None, progress: bool = True) -> TensorDictBase:
    """:func:`ensure_demonstrations` then :func:`load_transitions` on :func:`demonstration_dir`."""
    directory = demonstration_dir(cfg, run_dir)
    try:
        ensure_demonstrations(cfg, directory, progress=progress)
        return load_transitions(cfg, directory)
    except ValueError as e:  # a dataset of another world or mentor, a corrupt chunk: say which setting led there
        raise ValueError(f"demonstrations in {directory} (data.path={cfg.data.path}): {e}") from e


def data_totals(demos: TensorDictBase) -> dict[str, float]:
    """What the demonstrations hold: transitions, episodes ended in them, and their summed cost (the
    mentor's safety violations while recording)."""
    nxt = demos.get("next")
    return {"demo_steps": float(demos.numel()), "demo_episodes": float(nxt.get("done").sum()),
            "demo_safety_violations": float(nxt.get("cost").sum())}
