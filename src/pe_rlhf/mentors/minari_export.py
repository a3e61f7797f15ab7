"""Demonstrations to and from Minari, Farama's offline-RL dataset format (``pip install "pe-rlhf[minari]"``).

:func:`export_minari` writes a dataset directory of :mod:`pe_rlhf.mentors.recording` as a Minari dataset
(HDF5) that ``minari.load_dataset`` reads; :func:`import_minari` appends a Minari dataset's episodes to a
dataset directory. :func:`write_minari` / :func:`read_minari` do the same for any episodes as
TensorDicts (batch ``[T]``, TorchRL layout, e.g. rollouts through the intervention transform). An
episode of ``T`` steps maps as follows (TensorDict key -> Minari field):

- ``observation`` and the last ``("next", "observation")`` -> ``observations`` ``(T+1, D)`` float32;
- the executed action -> ``actions`` ``(T, 2)`` float32: ``("next", "behavior_action")`` where the
  episode holds it (then the root ``action``, the agent's proposal, -> ``infos["agent_action"]``),
  else the root ``action`` (a mentor-only recording: the mentor's executed action);
- ``("next", "reward")`` -> ``rewards`` ``(T,)`` float32; ``("next", "terminated" | "truncated")`` ->
  ``terminations`` / ``truncations`` ``(T,)`` bool;
- every other ``next`` entry -> ``infos[name]``, ``(T+1,)`` or ``(T+1, k)``, its own dtype: the step
  info (``cost``, ``success``, ``crash_vehicle``, ..., ``scene_seed``) and, where recorded, the
  takeover flags (``intervention``, ``intervention_start``, ``intervention_cost``, ``mentor_action``,
  ``physics_action``, ``mentor_selected``). Row 0 is the reset's info (Minari's infos have one row
  more than steps): the episode's first root value where it holds one (a TorchRL rollout; a
  recording's ``scene_seed``), else zeros (not recorded); reading back keeps rows 1.. under ``next``;
- the scene seed -> the episode's reset ``options`` ``{"scene_seed": s}``; other manifest fields
  (``cut``) -> the episode's metadata.

The dataset's ``env_spec`` is ``pe_rlhf/Driving-v0`` with the recorded DrivingConfig
(``dataset.recover_environment()`` rebuilds the world), ``algorithm_name`` is the mentor, and the
metadata's ``pe_rlhf`` entry is the directory's ``metadata.json``. A dataset directory holds no takeover
flags or agent actions (mentor-only driving): importing keeps the recording's keys only.

Where a dataset lives (``target`` / ``source``): a NAME, a Minari id ``[namespace/]name-vN``, under
``$MINARI_DATASETS_PATH`` (default ``~/.minari/datasets``); a PATH (starting with ``/``, ``.`` or
``~``) is the dataset's own folder, its last part the id (``name-vN``): ``minari.MinariDataset(PATH /
"data")`` opens it, and so does ``minari.load_dataset(id)`` with ``MINARI_DATASETS_PATH`` its parent. A
relative PATH is relative to the current directory (``./exports/professional-v0``).

Writing is all or nothing: the dataset is written into a hidden staging folder beside its destination
(``.<name>.partial-<pid>-<hex>``) and moved into place by one rename once complete; on any failure the staging
folder is removed, so a failed export leaves nothing behind and the same command can be run again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import uuid
import warnings
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from pe_rlhf import __version__
from pe_rlhf.envs import ENV_ID, DrivingConfig
from pe_rlhf.mentors.recording import (
    MANIFEST_FIELDS,
    DemonstrationRecorder,
    load_demonstrations,
    read_manifest,
    read_metadata,
)

STEP_FIELDS = ("observation", "reward", "done", "terminated", "truncated", "behavior_action")  # not infos
AGENT_ACTION = "agent_action"
RECOMPUTED = (*MANIFEST_FIELDS, "return", "cost", "success")  # manifest fields write_episode writes itself
MINARI_EPISODE_ATTRS = ("id", "seed", "total_steps", "options")
# Minari's advice to name an author, a code link and an evaluation env: not known here
_ADVICE = r"`(author|author_email|code_permalink|eval_env)` is set to None"


def _minari():
    try:
        import minari
    except ImportError as err:
        raise ImportError(f"Minari export needs the minari package ({err}): pip install 'pe-rlhf[minari]'") from err
    return minari


def _is_path(target: str) -> bool:
    return target.startswith(("/", ".", "~")) or os.path.isabs(target)


def resolve(target: str) -> tuple[str, Path | None]:
    """``(dataset_id, root)``: ``root`` is None for a NAME (Minari's own root), else the PATH's parent."""
    _minari()
    from minari.dataset.minari_dataset import parse_dataset_id

    path = Path(target).expanduser().absolute()  # relative to the current directory, once (Minari joins again)
    dataset_id = path.name if _is_path(target) else target
    try:
        parse_dataset_id(dataset_id)
    except (ValueError, TypeError):  # TypeError: no -vN (minari 0.5 parses the version as int(None))
        what = ("a PATH's last part must be a Minari dataset id name-vN, e.g. ./exports/professional-v0"
                if _is_path(target) else "a NAME must be a Minari dataset id [namespace/]name-vN, e.g. "
                "pe-rlhf/professional-v0")
        raise ValueError(f"{target!r}: {what}") from None
    return dataset_id, (path.parent if _is_path(target) else None)


@contextlib.contextmanager
def _datasets_root(root: Path | None) -> Iterator[None]:
    """``MINARI_DATASETS_PATH`` set to ``root`` for the block (Minari creates datasets under it)."""
    if root is None:
        yield
        return
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous


def datasets_root(root: Path | None) -> Path:
    """The absolute folder a dataset id is created under: ``root`` (a PATH's parent), else Minari's own
    (``$MINARI_DATASETS_PATH``, default ``~/.minari/datasets``)."""
    if root is not None:
        return Path(root).absolute()
    from minari.storage.datasets_root_dir import get_dataset_path

    return get_dataset_path().expanduser().absolute()


@contextlib.contextmanager
def staged(dataset_id: str, root: Path) -> Iterator[Path]:
    """A fresh staging root beside ``root / dataset_id``: the block writes the dataset under it; on success the
    first folder of ``dataset_id`` that ``root`` lacks (the dataset's, or a new namespace's) is renamed into
    place, on failure the staging root is removed. The destination must not exist yet."""
    final = root / dataset_id
    if final.exists():
        raise ValueError(f"{final}: a dataset already exists there; choose another name or version (-vN)")
    root.mkdir(parents=True, exist_ok=True)
    staging = root / f".{Path(dataset_id).name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    staging.mkdir()
    try:
        yield staging
        parts = Path(dataset_id).parts
        first_new = next(i for i in range(len(parts)) if not (root.joinpath(*parts[:i + 1])).exists())
        os.rename(staging.joinpath(*parts[:first_new + 1]), root.joinpath(*parts[:first_new + 1]))
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def open_minari(source: str):
    """The ``minari.MinariDataset`` named by ``source`` (NAME or PATH; a PATH may also be its ``data`` folder)."""
    minari = _minari()
    if not _is_path(source):
        return minari.load_dataset(source)
    path = Path(source).expanduser()
    for data in (path / "data", path):
        if (data / "metadata.json").is_file():
            return minari.MinariDataset(data)
    raise FileNotFoundError(f"{source}: no Minari dataset there (no data/metadata.json)")


# -- TensorDict episodes <-> Minari episodes --------------------------------------------------------------------------
def _column(td: TensorDictBase, key) -> np.ndarray:
    value = td.get(key).detach().cpu().numpy()
    return value.reshape(len(value)) if value.ndim == 2 and value.shape[1] == 1 else value


def _infos(td: TensorDictBase) -> dict[str, np.ndarray]:
    """``(T+1, ...)`` info arrays: the ``next`` entries besides the step fields, after a reset row (the
    root's first value where the episode has it, as a TorchRL rollout does; else zeros)."""
    nxt = td.get("next")
    infos = {k: _column(nxt, k) for k in nxt.keys() if k not in STEP_FIELDS and isinstance(nxt.get(k), torch.Tensor)}
    if ("next", "behavior_action") in td.keys(True):
        infos[AGENT_ACTION] = _column(td, "action")
    first = {k: _column(td[:1], k) for k in infos if k != AGENT_ACTION and isinstance(td.get(k, None), torch.Tensor)}
    return {k: np.concatenate([first[k].astype(v.dtype) if k in first else np.zeros_like(v[:1]), v])
            for k, v in infos.items()}


def episode_buffer(td: TensorDictBase, index: int):
    """One episode (batch ``[T]``) as a ``minari.data_collector.EpisodeBuffer`` (module docstring's mapping)."""
    from minari.data_collector import EpisodeBuffer

    obs, next_obs = td.get("observation"), td.get(("next", "observation"))
    if not torch.equal(obs[1:], next_obs[:-1]):
        raise ValueError(f"episode {index}: next observations do not follow on from observations "
                         "(not one episode); Minari stores one observation sequence per episode")
    executed = ("next", "behavior_action") if ("next", "behavior_action") in td.keys(True) else "action"
    seed = td.get("scene_seed", None)
    return EpisodeBuffer(
        id=index, options=None if seed is None else {"scene_seed": int(seed.reshape(-1)[0])},
        observations=np.concatenate([obs.numpy(), next_obs[-1:].numpy()]).astype(np.float32),
        actions=_column(td, executed).astype(np.float32), rewards=_column(td, ("next", "reward")).astype(np.float32),
        terminations=_column(td, ("next", "terminated")).astype(bool),
        truncations=_column(td, ("next", "truncated")).astype(bool), infos=_infos(td))


def episode_tensordict(episode, scene_seed: int | None = None) -> TensorDict:
    """A ``minari.EpisodeData`` as a TensorDict of batch ``[T]`` (the inverse of :func:`episode_buffer`)."""
    t = len(episode)
    obs = torch.as_tensor(np.asarray(episode.observations))
    actions = torch.as_tensor(np.asarray(episode.actions)).reshape(t, -1)
    terminated = torch.as_tensor(np.asarray(episode.terminations, dtype=bool)).reshape(t, 1)
    truncated = torch.as_tensor(np.asarray(episode.truncations, dtype=bool)).reshape(t, 1)
    nxt: dict[str, torch.Tensor] = {
        "observation": obs[1:], "reward": torch.as_tensor(np.asarray(episode.rewards)).reshape(t, 1),
        "terminated": terminated, "truncated": truncated, "done": terminated | truncated}
    root = {"observation": obs[:-1], "action": actions}
    for key, value in (episode.infos or {}).items():
        if not isinstance(value, np.ndarray) or len(value) not in (t, t + 1):
            continue  # nested or odd-length infos of another tool: not ours to map
        value = torch.as_tensor(value[len(value) - t:]).reshape(t, -1)  # drop the reset row if there is one
        if key == AGENT_ACTION:
            root["action"], nxt["behavior_action"] = value, actions
        else:
            nxt[key] = value
    if scene_seed is None and "scene_seed" in nxt:
        scene_seed = int(nxt["scene_seed"][0, 0])
    if scene_seed is not None:
        root["scene_seed"] = torch.full((t, 1), int(scene_seed), dtype=torch.int64)
    return TensorDict({**root, "next": nxt}, batch_size=[t])


def write_minari(episodes: Iterable[TensorDictBase], target: str, *, env_config: DrivingConfig, mentor: str,
                 metadata: dict[str, Any] | None = None, episode_metadata: Iterable[dict] | None = None,
                 description: str | None = None):
    """Write ``episodes`` (TensorDicts, batch ``[T]``) as a new Minari dataset at ``target`` (NAME or PATH);
    returns the ``minari.MinariDataset``. ``metadata`` is stored as the dataset's ``pe_rlhf`` entry,
    ``episode_metadata`` (one dict per episode) as each episode's metadata."""
    import gymnasium as gym

    minari = _minari()
    dataset_id, root = resolve(target)
    buffers = [episode_buffer(td, i) for i, td in enumerate(episodes)]
    if not buffers:
        raise ValueError("write_minari: no episodes to write")
    obs_size = buffers[0].observations.shape[-1]
    env_spec = dataclasses.replace(gym.spec(ENV_ID), kwargs={"config": env_config.to_dict()})
    root = datasets_root(root)
    with staged(dataset_id, root) as staging, _datasets_root(staging), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_ADVICE, category=UserWarning)
        dataset = minari.create_dataset_from_buffers(
            dataset_id, buffers, env=env_spec, algorithm_name=mentor, data_format="hdf5",
            observation_space=gym.spaces.Box(-1.0, 1.0, (obs_size,), dtype=np.float32),
            action_space=gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32), requirements=[f"pe-rlhf>={__version__}"],
            description=description or f"pe_rlhf driving demonstrations by {mentor}")
        dataset.storage.update_metadata({"pe_rlhf": dict(metadata or {})})
        episode_metadata = [dict(m) for m in episode_metadata or ()]
        if any(episode_metadata):
            dataset.storage.update_episode_metadata(episode_metadata, range(len(episode_metadata)))
    return minari.MinariDataset(root / dataset_id / "data")


def read_minari(source: str) -> Iterator[tuple[TensorDict, dict[str, Any]]]:
    """Each episode of the Minari dataset ``source`` as ``(TensorDict [T], its episode metadata)``."""
    dataset = open_minari(source)
    metas = list(dataset.storage.get_episode_metadata(dataset.episode_indices))
    for episode, meta in zip(dataset.iterate_episodes(), metas):
        seed = (meta.get("options") or {}).get("scene_seed")
        yield episode_tensordict(episode, None if seed is None else int(seed)), meta


# -- dataset directories <-> Minari datasets -----------------------------------------------------------------------
def directory_episodes(directory: str | Path) -> list[TensorDict]:
    """The complete episodes of a dataset directory, in order, one TensorDict each (batch ``[T]``)."""
    data = load_demonstrations(directory).storage[:]
    counts = torch.unique_consecutive(data.get("episode").reshape(-1), return_counts=True)[1]
    return list(data.split(counts.tolist()))


def export_minari(directory: str | Path, target: str, *, description: str | None = None) -> dict[str, Any]:
    """Write the dataset directory as the Minari dataset ``target`` (NAME or PATH; must not exist yet).
    Returns ``dataset_id``, ``path`` (its ``data`` folder), ``episodes``, ``steps``."""
    meta = read_metadata(directory)
    extras = [{k: v for k, v in e.items() if k not in RECOMPUTED and isinstance(v, (bool, int, float, str))}
              for e in read_manifest(directory)]
    episodes = directory_episodes(directory)
    dataset = write_minari(episodes, target, env_config=DrivingConfig.from_dict(meta["env_config"]),
                           mentor=str(meta["mentor"]), metadata=meta, episode_metadata=extras,
                           description=description or f"pe_rlhf demonstrations by {meta['mentor']} "
                           f"(split {meta.get('split')}), exported from {directory}")
    return {"dataset_id": dataset.id, "path": str(dataset.storage.data_path),
            "episodes": dataset.total_episodes, "steps": dataset.total_steps}


def _world(dataset, source: str, mentor: str | None) -> tuple[DrivingConfig, str, list[int] | None, str | None]:
    """DrivingConfig, mentor, seeds and split of a Minari dataset (ours: its ``pe_rlhf`` metadata)."""
    metadata = dataset.storage.metadata
    meta, env_spec = metadata.get("pe_rlhf") or {}, dataset.env_spec
    if "env_config" in meta:
        config = meta["env_config"]
    elif env_spec is not None and env_spec.id == ENV_ID:
        config = env_spec.kwargs.get("config") or {}
    else:
        env_id = None if env_spec is None else env_spec.id
        raise ValueError(f"{source}: recorded in {env_id!r}, not in {ENV_ID}; only driving datasets can be "
                         "imported")
    name = mentor or meta.get("mentor") or metadata.get("algorithm_name") or "minari"
    return DrivingConfig.from_dict(config), str(name), meta.get("seeds"), meta.get("split")


def import_minari(source: str, directory: str | Path, *, mentor: str | None = None) -> dict[str, Any]:
    """Append the episodes of the Minari dataset ``source`` (NAME or PATH) to the dataset directory
    (created, or continued when its metadata matches; see :class:`DemonstrationRecorder`). ``mentor``
    overrides the recorded mentor's name. Returns ``episodes`` and ``steps`` added."""
    dataset = open_minari(source)
    config, name, seeds, split = _world(dataset, source, mentor)
    if seeds is None:  # not ours: the scenes the episodes were driven on
        seeds = list(dict.fromkeys(int(td.get("scene_seed")[0]) for td, _ in read_minari(source)
                                   if "scene_seed" in td.keys())) or None
    added = steps = 0
    with DemonstrationRecorder(directory, config, name, seeds, split=split) as recorder:
        for td, meta in read_minari(source):
            extra = {k: v.item() if hasattr(v, "item") else v for k, v in meta.items()
                     if k not in MINARI_EPISODE_ATTRS and k not in RECOMPUTED}
            recorder.write_episode(td, **extra)
            added, steps = added + 1, steps + td.numel()
    return {"episodes": added, "steps": steps}


__all__ = ["directory_episodes", "episode_buffer", "episode_tensordict", "export_minari", "import_minari",
           "open_minari", "read_minari", "resolve", "write_minari"]
