"""The selector's value source: a frozen, reward-trained expert's critics (the authors' design) or a warm-up fit.

``selector.value`` names it:

- ``expert`` (default): the expert shipped with the package, ``pe_rlhf/data/value_expert.safetensors`` (provenance
  beside it in ``value_expert.json``: command, config, seed, steps, test success, sha256);
- ``expert:PATH``: a Q-ensemble file (:func:`~pe_rlhf.modules.save_q_ensemble`, e.g. one written by
  :func:`export_value_expert`), or a run folder (a ``recipes/sac_rs`` baseline run, or a PE-RLHF/HACO run)
  whose newest checkpoint's critics and their targets become the members;
- ``warmup``: a ``QEnsemble`` fitted on the warm-up data (this project's first design; it sees no failure).

An expert is loaded with ``weights_only=True``, frozen, and shape-checked against the env's observation.
The reason for the expert: fitted on near-noiseless warm-up driving, the ensemble has never seen a crash, so
it cannot know that an action is bad; a SAC critic trained on the env reward has.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import torch

from pe_rlhf.durable import sha256_file
from pe_rlhf.modules import QEnsemble, load_q_ensemble, q_ensemble_from_critics, save_q_ensemble

VALUE_SOURCES = ("expert", "expert:PATH", "warmup", "forecast")
PACKAGED_EXPERT = "value_expert.safetensors"
PROVENANCE_SUFFIX = ".json"
CRITIC_PREFIXES = ("qvalue_network_params.", "target_qvalue_network_params.")


def packaged_expert_path() -> Path:
    """The expert shipped with the package (``pe_rlhf/data/value_expert.safetensors``)."""
    return Path(str(resources.files("pe_rlhf") / "data" / PACKAGED_EXPERT))


def parse_value_source(text: str) -> tuple[str, Path | None]:
    """``("warmup", None)``, ``("expert", None)`` (the packaged expert), ``("expert", PATH)`` or
    ``("forecast", None)`` (the physics forecast, :class:`~pe_rlhf.physics.SafetyForecastValue`); a
    ``ValueError`` naming the allowed forms otherwise."""
    text = str(text).strip()
    if text in ("warmup", "forecast"):
        return text, None
    if text == "expert":
        return "expert", None
    if text.startswith("expert:") and text[len("expert:"):].strip():
        return "expert", Path(text[len("expert:"):].strip()).expanduser()
    raise ValueError(f"selector.value={text!r}; allowed: {list(VALUE_SOURCES)}")


def _critic_stacks(tensors: dict[str, Any], where: Path) -> list[dict[str, torch.Tensor]]:
    loss = tensors.get("modules", {}).get("loss") if isinstance(tensors, dict) else None
    if not isinstance(loss, dict):
        raise ValueError(f"{where}: no 'loss' module state (not a training checkpoint)")
    stacks = [{k[len(p):]: v for k, v in loss.items() if k.startswith(p)} for p in CRITIC_PREFIXES]
    stacks = [s for s in stacks if s]
    if not stacks:
        raise ValueError(f"{where}: the loss state has no critics ({', '.join(CRITIC_PREFIXES)})")
    return stacks


def critics_of_run(run_dir: str | Path, max_members: int | None = None) -> QEnsemble:
    """The critics of the newest checkpoint of a run folder (or of a checkpoint folder) as a frozen
    ``QEnsemble``: online copies first, then their targets (SAC's twin: 4 members)."""
    from pe_rlhf.runtime.checkpoint import TENSORS, find_checkpoint

    run_dir = Path(run_dir)
    ckpt = find_checkpoint(run_dir / "checkpoints") or find_checkpoint(run_dir)
    if ckpt is None:
        raise FileNotFoundError(f"{run_dir}: no complete checkpoint (neither {run_dir / 'checkpoints'} nor the "
                                "folder itself holds one)")
    path = ckpt / TENSORS
    try:
        tensors = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # corrupt or foreign: say which file
        raise ValueError(f"cannot read {path}: {type(e).__name__}: {str(e)[:200]}") from None
    return q_ensemble_from_critics(*_critic_stacks(tensors, path), max_members=max_members)


def load_value_expert(source: str | Path | None, obs_dim: int, max_members: int | None = None) -> QEnsemble:
    """A frozen expert ``QEnsemble`` from ``source`` (None: the packaged one; a Q-ensemble file; a run or
    checkpoint folder) whose observation width must be ``obs_dim`` (a ``ValueError`` saying both widths
    otherwise). ``max_members`` keeps the first members only (``selector.num_members``)."""
    path = packaged_expert_path() if source is None else Path(source)
    if not path.exists():
        raise FileNotFoundError(f"value expert {str(path)!r} does not exist")
    if path.is_dir():
        ensemble = critics_of_run(path, max_members)
    else:
        ensemble = load_q_ensemble(path)
        if max_members is not None and max_members < ensemble.num_members:
            params = {k: v[:max_members] for k, v in
                      ensemble.ensemble.params_td.flatten_keys(".").items()}
            ensemble = q_ensemble_from_critics(params, action_dim=ensemble.action_dim)
    if ensemble.obs_dim != int(obs_dim):
        raise ValueError(f"value expert {str(path)!r} reads observations of width {ensemble.obs_dim}, the env gives "
                         f"{int(obs_dim)} (env.lane_features / env.lidar_beams differ from the expert's run)")
    return ensemble.requires_grad_(False).eval()


def export_value_expert(run_dir: str | Path, out_file: str | Path, provenance: dict[str, Any] | None = None) -> dict:
    """Write the critics of ``run_dir``'s newest checkpoint as a Q-ensemble file ``out_file`` and its provenance
    (``provenance`` plus the run's config, members, observation width, sha256 of the file) beside it as
    ``<out_file>.json``; returns the provenance."""
    from omegaconf import OmegaConf

    run_dir, out_file = Path(run_dir), Path(out_file)
    ensemble = critics_of_run(run_dir)
    out_file.parent.mkdir(parents=True, exist_ok=True)
    save_q_ensemble(ensemble, out_file)
    config = run_dir / "config.yaml"
    record = {
        **(provenance or {}),
        "run_config": OmegaConf.to_container(OmegaConf.load(config)) if config.exists() else None,
        "members": ensemble.num_members,
        "members_are": "the run's online critics, then their target copies",
        "obs_dim": ensemble.obs_dim,
        "hidden": list(ensemble.hidden),
        "file": out_file.name,
        "sha256": sha256_file(out_file),
    }
    out_file.with_suffix(PROVENANCE_SUFFIX).write_text(json.dumps(record, indent=2) + "\n")
    return record


__all__ = ["PACKAGED_EXPERT", "VALUE_SOURCES", "critics_of_run", "export_value_expert", "load_value_expert",
           "packaged_expert_path", "parse_value_source"]
