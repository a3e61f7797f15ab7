"""Load a trained agent from a run folder (for ``pe-rlhf evaluate --checkpoint DIR``)."""

from __future__ import annotations

from pathlib import Path

import torch

from pe_rlhf.training import builders


def run_world(run_dir: str | Path):
    """The :class:`~pe_rlhf.envs.config.DrivingConfig` the run in ``run_dir`` trained in (its ``env`` group):
    its agent must be evaluated with the same observation (``lane_features``, ``lidar_beams``)."""
    from pe_rlhf.training.config import driving_config, load_config

    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").exists():
        raise FileNotFoundError(f"{run_dir} is not a training run folder (no config.yaml)")
    return driving_config(load_config(run_dir / "config.yaml", apply_profile=False))


def load_actor(run_dir: str | Path):
    """The actor of the run in ``run_dir``: its final ``actor.pt`` if the run finished, else the actor in
    its newest checkpoint. Reads ``config.yaml`` for the network sizes; loads with ``weights_only=True``.
    """
    from pe_rlhf.training.checkpoint import load_checkpoint
    from pe_rlhf.training.config import load_config

    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").exists():
        raise FileNotFoundError(f"{run_dir} is not a training run folder (no config.yaml)")
    cfg = load_config(run_dir / "config.yaml", apply_profile=False)
    actor = builders.build_actor(cfg)
    final = run_dir / "actor.pt"
    if final.exists():
        try:
            state = torch.load(final, weights_only=True, map_location="cpu")
            actor.load_state_dict(state)
        except Exception as e:  # a corrupt or foreign file: say which
            raise ValueError(f"cannot load the actor from {final}: {type(e).__name__}: {str(e)[:200]}") from None
        return actor
    loss, _ = builders.build_loss(cfg, actor)
    load_checkpoint(run_dir / "checkpoints", modules={"loss": loss}, optimizers={}, strict=False,
                    restore_rng_state=False)
    return actor
