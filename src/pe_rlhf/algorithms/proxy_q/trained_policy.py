"""Load a trained agent from a run folder (for ``pe-rlhf evaluate --checkpoint DIR`` and the expert-policy
warm-up, ``collector.warmup_policy``).

A run folder is a PE-RLHF/HACO/HAIM-DRL run (``config.yaml`` of the recipe config) or a baseline run
(``config.yaml`` of the baseline's config, with a top-level ``method``, e.g. ``sac_rs``); its ``config.yaml``
records which by the method's registry name (``algorithm: pe-rlhf``, ``algorithm: sac-rs``); a run folder
written before that record is a baseline's when its config names a ``method``. :func:`run_world` and
:func:`load_run_actor` read both kinds.
"""

from __future__ import annotations

import warnings
from pathlib import Path


from pe_rlhf import durable
from pe_rlhf.runtime.run import ACTOR_FILE
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.algorithms.proxy_q import model_builders as builders

LEGACY_ACTOR_FILE = "actor.pt"  # a run's actor before safetensors (torch.save; loaded with weights_only=True)


def _baseline_method(run_dir: Path) -> str | None:
    """The baseline method (``sac_rs``, ...) a run folder's ``config.yaml`` names, or None for a
    PE-RLHF/HACO/HAIM-DRL run."""
    from omegaconf import OmegaConf

    from pe_rlhf.runtime.config import ALGORITHM_KEY
    from pe_rlhf.algorithms.proxy_q.config import PROXY_Q_ALGORITHMS

    if not (run_dir / "config.yaml").exists():
        raise FileNotFoundError(f"{run_dir} is not a training run folder (no config.yaml)")
    config = OmegaConf.load(run_dir / "config.yaml")
    algorithm = config.get(ALGORITHM_KEY)
    if algorithm is not None:  # the run recorded its method: a baseline's registry name is its recipe's, dashed
        return None if algorithm in PROXY_Q_ALGORITHMS else str(algorithm).replace("-", "_")
    method = config.get("method")  # a run folder from before the record
    return None if method is None else str(method)


def saved_run_config(run_dir: str | Path):
    """The config a run in ``run_dir`` (either kind) ran with, as its ``config.yaml`` saved it."""
    run_dir = Path(run_dir)
    if _baseline_method(run_dir) is not None:  # saved whole by the run: read as written
        from omegaconf import OmegaConf

        return OmegaConf.load(run_dir / "config.yaml")
    from pe_rlhf.algorithms.proxy_q.config import load_config

    return load_config(run_dir / "config.yaml", apply_profile=False)


def run_world(run_dir: str | Path):
    """The :class:`~pe_rlhf.envs.config.DrivingConfig` the run in ``run_dir`` (either kind) trained in (its
    ``env`` group): its agent must be evaluated with the same observation (``lane_features``, ``lidar_beams``)."""
    from pe_rlhf.runtime.config import driving_config

    return driving_config(saved_run_config(Path(run_dir)))


def run_observation_size(run_dir: str | Path) -> int:
    """The observation width the actor of the run in ``run_dir`` (either kind) reads."""
    return obs_dim(saved_run_config(Path(run_dir)))


def load_run_actor(run_dir: str | Path):
    """The trained actor of a run folder of either kind: :func:`load_actor` for a PE-RLHF/HACO/HAIM-DRL
    run; for a baseline run its actor (``actor.safetensors``, or a legacy ``actor.pt`` loaded with ``weights_only=True``) in :func:`pe_rlhf.modules.make_actor`
    sized by its saved ``config.yaml`` (``loss.hidden``, the ``env`` group's observation)."""
    run_dir = Path(run_dir)
    if _baseline_method(run_dir) is None:
        return load_actor(run_dir)
    from pe_rlhf.modules import make_actor

    final = actor_file(run_dir)
    if final is None:
        raise FileNotFoundError(f"{run_dir}: the baseline run has no {LEGACY_ACTOR_FILE} or {ACTOR_FILE} (it has "
                                "not finished)")
    cfg = saved_run_config(run_dir)
    actor = make_actor(obs_dim(cfg), hidden=tuple(cfg.loss.hidden))
    actor.load_state_dict(load_weights(final))
    return actor


def actor_file(run_dir: Path) -> Path | None:
    """A finished run's actor: ``actor.safetensors``, or a run's from before it, ``actor.pt``; None if neither."""
    for name in (ACTOR_FILE, LEGACY_ACTOR_FILE):
        if (run_dir / name).is_file():
            return run_dir / name
    return None


def load_weights(path: Path) -> dict:
    """A state dict saved by a run (safetensors, or a legacy torch file loaded with ``weights_only=True``);
    ValueError in one line naming ``path`` and what is wrong when it is truncated, corrupt or not plain tensor data
    (never torch's advice to load unsafely)."""
    return durable.load_tensors(path)[0]


def load_actor(run_dir: str | Path, checkpoint: str | Path | None = None):
    """The actor of the run in ``run_dir``: its final actor (:func:`actor_file`) if the run finished, else the actor in
    its newest checkpoint; with ``checkpoint`` (a ``ckpt_<step>`` folder), that checkpoint's actor. Reads
    ``config.yaml`` for the network sizes; loads with ``weights_only=True``.
    """
    from pe_rlhf.runtime.checkpoint import load_checkpoint
    from pe_rlhf.algorithms.proxy_q.config import load_config

    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").exists():
        raise FileNotFoundError(f"{run_dir} is not a training run folder (no config.yaml)")
    cfg = load_config(run_dir / "config.yaml", apply_profile=False)
    actor = builders.build_actor(cfg)
    final = actor_file(run_dir)
    if checkpoint is None and final is not None:
        state = load_weights(final)
        try:
            actor.load_state_dict(state)
        except Exception as e:  # a foreign file: say which
            raise ValueError(f"cannot load the actor from {final}: {type(e).__name__}: {str(e)[:200]}") from None
        return actor
    loss, _ = builders.build_loss(cfg, actor)
    with warnings.catch_warnings():  # a checkpoint asked for by name: that later ones exist is no news
        if checkpoint is not None:
            warnings.filterwarnings("ignore", message=r"loading ckpt_\d+, but .* have larger steps")
        load_checkpoint(run_dir / "checkpoints" if checkpoint is None else checkpoint, modules={"loss": loss},
                        optimizers={}, strict=False, restore_rng_state=False)
    return actor
