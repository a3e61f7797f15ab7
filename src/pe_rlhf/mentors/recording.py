"""Crash-safe recording of mentor-only driving (the warm-up demonstrations, spec section 1).

TensorDict layout of every step (batch ``[T]``; TorchRL convention, root = s_t, ``next`` = s_{t+1}):

- root: ``observation`` float32 ``(250,)``, ``action`` float32 ``(2,)`` (the executed mentor
  action, in [-1, 1]), ``done``/``terminated``/``truncated`` bool ``(1,)`` (all False),
  ``episode`` and ``scene_seed`` int64 ``(1,)``;
- ``next``: ``observation`` float32 ``(250,)``, ``reward`` float32 ``(1,)``, ``done``/``terminated``/
  ``truncated`` bool ``(1,)``, and the step info ``cost``, ``route_completion``, ``travel_distance``,
  ``velocity`` float32 ``(1,)``; ``success``, ``crash_vehicle``, ``crash_object``, ``out_of_road``
  bool ``(1,)``; ``overtakes``, ``scene_seed`` int64 ``(1,)``.

On disk (``directory/``): ``metadata.json`` (written once, atomically); ``episodes/NNNNNN.pt``, one
``torch.save`` of ``td.to_dict()`` (plain tensors, loaded with ``weights_only=True``) per finished
episode, written to a temp file, fsync'd and renamed; ``manifest.jsonl``, one fsync'd line per
complete episode (file, steps, scene seed, return, cost, success, bytes, sha256). An episode
exists only once its manifest line does: a kill loses at most the episode being driven, and a
chunk without a manifest line is ignored by loaders and deleted when a recorder reopens the
directory. Reopening continues the episode numbering and the scene-seed cycle.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import time
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from tqdm.auto import tqdm

from pe_rlhf import __version__
from pe_rlhf.envs import DrivingConfig, make_gym_env, scene_seeds
from pe_rlhf.envs.torchrl_env import BOOL_INFO, FLOAT_INFO, INT_INFO
from pe_rlhf.durable import replace_bytes, write_bytes
from pe_rlhf.filelock import FileLock

FORMAT_VERSION = 1
DONE_KEYS = ("done", "terminated", "truncated")
ROOT_KEYS = ("observation", "action", *DONE_KEYS, "episode", "scene_seed")
INFO_KEYS = (*FLOAT_INFO, *BOOL_INFO, *INT_INFO)
NEXT_KEYS = ("observation", "reward", *DONE_KEYS, *INFO_KEYS)
MANIFEST_FIELDS = ("episode", "file", "steps", "scene_seed", "bytes", "sha256")
CHUNK_NAME = re.compile(r"^\.?\d{6}\.pt(\.tmp)?$")  # episodes/NNNNNN.pt and its temp file
DTYPES = {**dict.fromkeys(("observation", "next_observation", "action", "reward", *FLOAT_INFO), torch.float32),
          **dict.fromkeys(("terminated", "truncated", *BOOL_INFO), torch.bool), **dict.fromkeys(INT_INFO, torch.int64)}


def _missing_keys(td: TensorDictBase) -> list[str]:
    keys = set(td.keys(True))
    return [k for k in ROOT_KEYS if k not in keys] + [f"next.{k}" for k in NEXT_KEYS if ("next", k) not in keys]


def read_metadata(directory: str | Path) -> dict[str, Any]:
    """The dataset's ``metadata.json``; FileNotFoundError if there is none, ValueError if it is corrupt."""
    path = Path(directory) / "metadata.json"
    if not path.is_file():
        raise FileNotFoundError(f"{directory} is not a demonstration dataset (no {path.name})")
    try:
        meta = json.loads(path.read_text())
        meta["env_config"], meta["mentor"]  # noqa: B018 - required fields
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"corrupt dataset metadata {path}: {e!r}") from None
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {meta['format_version']} is newer than this "
                         f"pe_rlhf ({FORMAT_VERSION}); upgrade pe_rlhf")
    return meta


def read_manifest(directory: str | Path) -> list[dict[str, Any]]:
    """The complete episodes, in order; a malformed line raises ValueError naming file and line."""
    path = Path(directory) / "manifest.jsonl"
    if not path.exists():
        return []
    entries: list[dict[str, Any]] = []
    data = path.read_bytes()
    lines = data.split(b"\n")
    for lineno, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        if lineno == len(lines) and not _is_manifest_line(line):  # no newline after it: a write a kill tore
            warnings.warn(f"{path} line {lineno} is torn (the recorder was killed while writing it): that "
                          f"episode is lost, the {len(entries)} before it are kept", stacklevel=2)
            break
        try:
            entry = json.loads(line)
            if not isinstance(entry, dict) or any(k not in entry for k in MANIFEST_FIELDS):
                raise ValueError(f"expected an object with {list(MANIFEST_FIELDS)}")
            if entry["episode"] != len(entries):
                raise ValueError(f"episode {entry['episode']} out of order (expected {len(entries)})")
        except ValueError as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            raise ValueError(f"corrupt manifest {path} line {lineno}: {e}; "
                             f"line starts {line[:60]!r}") from None
        entries.append(entry)
    return entries


def _is_manifest_line(line: bytes) -> bool:
    try:
        entry = json.loads(line)
    except ValueError:
        return False
    return isinstance(entry, dict) and all(k in entry for k in MANIFEST_FIELDS)


def _drop_torn_line(path: Path) -> None:
    """Rewrite a manifest whose last line is torn without it (before a reopened recorder appends after it)."""
    if path.exists():
        data = path.read_bytes()
        if data and not data.endswith(b"\n"):
            replace_bytes(path, data[: data.rfind(b"\n") + 1])


def _config_mismatches(recorded: dict, requested: DrivingConfig) -> list[str]:
    # Fields added to DrivingConfig after recording are taken to have had their default.
    recorded = {**DrivingConfig().to_dict(), **recorded}
    return [f"{k}: recorded {recorded.get(k)!r}, requested {v!r}"
            for k, v in requested.to_dict().items() if recorded.get(k) != v]


def _load_chunk(directory: Path, entry: dict[str, Any]) -> TensorDict:
    path = directory / entry["file"]
    if not path.is_file():
        raise ValueError(f"missing episode chunk {path} (listed in the manifest)")
    data = path.read_bytes()
    if len(data) != entry["bytes"]:
        raise ValueError(f"corrupt episode chunk {path}: {len(data)} bytes, the manifest says {entry['bytes']}")
    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise ValueError(f"corrupt episode chunk {path}: its sha256 differs from the manifest's")
    try:
        td = TensorDict(torch.load(io.BytesIO(data), weights_only=True), batch_size=[entry["steps"]])
        missing = _missing_keys(td)
    except Exception as e:  # any unpickling / shape error: name the file, not the stack
        raise ValueError(f"unreadable episode chunk {path}: {type(e).__name__}: {e}") from None
    if missing:
        raise ValueError(f"episode chunk {path} lacks keys {missing}")
    return td


def load_demonstrations(directory: str | Path, env_config: DrivingConfig | None = None) -> TensorDictReplayBuffer:
    """All complete episodes, in order, in a TensorDictReplayBuffer (LazyTensorStorage of their size)."""
    directory = Path(directory)
    meta = read_metadata(directory)
    if env_config is not None and (bad := _config_mismatches(meta["env_config"], env_config)):
        raise ValueError(f"dataset {directory} was recorded under a different DrivingConfig: " + "; ".join(bad))
    entries = read_manifest(directory)
    if not entries:
        raise ValueError(f"dataset {directory} has no complete episodes")
    chunks = [_load_chunk(directory, e) for e in entries]
    try:
        data = torch.cat(chunks)  # one extend: a buffer write per chunk costs ~30 ms
    except Exception as e:  # keys or shapes differ between chunks (e.g. written by another version)
        raise ValueError(f"episode chunks of {directory} do not fit together: {type(e).__name__}: {e}") from None
    del chunks
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), batch_size=None)
    buffer.extend(data)
    return buffer


def dataset_info(directory: str | Path) -> dict[str, Any]:
    """Summary from metadata and manifest (chunks are not read)."""
    meta, entries = read_metadata(directory), read_manifest(directory)
    n = len(entries)
    return {
        "directory": str(directory), "mentor": meta["mentor"], "split": meta.get("split"),
        "episodes": n, "steps": sum(e["steps"] for e in entries),
        "success_rate": sum(bool(e.get("success")) for e in entries) / n if n else 0.0,
        "mean_return": sum(e.get("return", 0.0) for e in entries) / n if n else 0.0,
        "mean_cost": sum(e.get("cost", 0.0) for e in entries) / n if n else 0.0,
        "created": meta.get("created"), "pe_rlhf_version": meta.get("pe_rlhf_version"),
    }


class DemonstrationRecorder:
    """Appends whole episodes to a dataset directory; see the module docstring for the layout.

    ``seeds``: the scene seeds to cycle through (default: the config's split); ``split`` is
    recorded for information. Reopening an existing directory checks mentor, seeds and env
    config against ``metadata.json`` (ValueError naming each mismatch unless ``allow_mismatch``),
    deletes chunks not in the manifest, and continues numbering and the seed cycle. One recorder
    per directory at a time (a :class:`~pe_rlhf.filelock.FileLock` on ``.lock``; released by the OS if the
    process dies).
    """

    def __init__(self, directory: str | Path, env_config: DrivingConfig | None = None, mentor_name: str = "mentor",
                 seeds: Sequence[int] | None = None, *, split: str | None = None, allow_mismatch: bool = False):
        self.directory = Path(directory)
        self.env_config = env_config or DrivingConfig()
        split = split or (self.env_config.split if seeds is None else None)
        seeds = [int(s) for s in (scene_seeds(split or "train") if seeds is None else seeds)]
        if not seeds:
            raise ValueError("DemonstrationRecorder needs at least one scene seed")
        (self.directory / "episodes").mkdir(parents=True, exist_ok=True)
        self._lock = FileLock(self.directory / ".lock")  # held until close()
        if not self._lock.acquire(blocking=False):
            raise RuntimeError(f"another process is recording into {self.directory}")
        try:
            self._open(mentor_name, seeds, split, allow_mismatch)
        except BaseException:
            self.close()
            raise
        self._steps: list[dict[str, Any]] = []

    def _open(self, mentor_name: str, seeds: list[int], split: str | None, allow_mismatch: bool) -> None:
        if (self.directory / "metadata.json").exists():
            self.metadata = read_metadata(self.directory)
            bad = _config_mismatches(self.metadata["env_config"], self.env_config)
            if self.metadata["mentor"] != mentor_name:
                bad.append(f"mentor: recorded {self.metadata['mentor']!r}, requested {mentor_name!r}")
            if self.metadata["seeds"] != seeds:
                bad.append(f"seeds: recorded {self.metadata['seeds']}, requested {seeds}")
            if bad and not allow_mismatch:
                raise ValueError(f"dataset {self.directory} was recorded differently: " + "; ".join(bad)
                                 + " (pass allow_mismatch=True to append anyway)")
        else:
            env = make_gym_env(self.env_config)
            obs_size = int(env.observation_space.shape[0])
            env.close()
            self.metadata = {
                "format_version": FORMAT_VERSION, "mentor": mentor_name, "split": split, "seeds": seeds,
                "env_config": self.env_config.to_dict(), "observation_size": obs_size,
                "pe_rlhf_version": __version__, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            }
            replace_bytes(self.directory / "metadata.json", json.dumps(self.metadata, indent=2).encode())
        self.seeds = seeds  # (the recorded ones unless allow_mismatch let other seeds through)
        self.entries = read_manifest(self.directory)
        _drop_torn_line(self.directory / "manifest.jsonl")  # the next line must not continue a torn one
        keep = {Path(e["file"]).name for e in self.entries}
        for p in (self.directory / "episodes").iterdir():  # killed mid-write: not in the manifest
            if p.name not in keep and CHUNK_NAME.match(p.name) and p.is_file():
                p.unlink()

    @property
    def episodes(self) -> int:
        return len(self.entries)

    @property
    def steps(self) -> int:
        return sum(e["steps"] for e in self.entries)

    def next_scene_seed(self) -> int:
        """The scene of the next episode: the seed cycle continues where the manifest ends."""
        return self.seeds[self.episodes % len(self.seeds)]

    def discard_episode(self) -> None:
        """Drop the buffered steps (``record`` calls it at every episode start)."""
        self._steps = []

    def add_step(self, obs, action, next_obs, reward: float, terminated: bool, truncated: bool, info: dict) -> None:
        """Buffer one transition of the current episode (in memory until ``end_episode``)."""
        self._steps.append({"observation": obs, "action": action, "next_observation": next_obs, "reward": reward,
                            "terminated": terminated, "truncated": truncated, **{k: info[k] for k in INFO_KEYS}})

    def end_episode(self, cut: bool = False) -> dict[str, Any] | None:
        """Write the buffered episode (``cut``: stopped early, its last step is marked truncated)."""
        rows, self._steps = self._steps, []
        if not rows:
            return None
        rows[-1]["truncated"] = bool(rows[-1]["truncated"] or (cut and not rows[-1]["terminated"]))
        t = len(rows)
        col = {k: torch.as_tensor(np.array([r[k] for r in rows])).to(dtype).reshape(t, -1)
               for k, dtype in DTYPES.items()}
        nxt = {k: col[k] for k in NEXT_KEYS if k in col}
        nxt.update(observation=col["next_observation"], done=col["terminated"] | col["truncated"])
        td = TensorDict({"observation": col["observation"], "action": col["action"],
                         "scene_seed": col["scene_seed"].clone(), "next": nxt}, batch_size=[t])
        return self.write_episode(td, cut=cut)

    def write_episode(self, td: TensorDictBase, **extra: Any) -> dict[str, Any]:
        """Persist one episode (batch ``[T]``, the module's keys; e.g. a TorchRL rollout); returns its manifest line."""
        if td.batch_dims != 1 or td.numel() == 0:
            raise ValueError(f"write_episode: expected one non-empty episode, batch [T]; got {list(td.batch_size)}")
        n, t = self.episodes, td.batch_size[0]
        td = td.select(*ROOT_KEYS, *(("next", k) for k in NEXT_KEYS), strict=False).clone()
        td.set("episode", torch.full((t, 1), n, dtype=torch.int64))
        for k in DONE_KEYS:  # a plain rollout's root done flags are False (s_t is never terminal)
            td.setdefault(k, torch.zeros(t, 1, dtype=torch.bool))
        td.setdefault("scene_seed", td.get(("next", "scene_seed"), torch.full((t, 1), -1)).clone())
        if missing := _missing_keys(td):
            raise ValueError(f"write_episode: episode lacks keys {missing}")
        if td.get("observation").shape[-1] != self.metadata["observation_size"]:
            raise ValueError(f"write_episode: observation size {td.get('observation').shape[-1]}, "
                             f"dataset has {self.metadata['observation_size']}")
        buf = io.BytesIO()
        torch.save(td.to_dict(), buf)
        data = buf.getvalue()
        rel = f"episodes/{n:06d}.pt"
        target = self.directory / rel
        replace_bytes(target, data, tmp=target.with_name(f".{target.name}.tmp"))
        nxt = td.get("next")
        entry = {"episode": n, "file": rel, "steps": t, "scene_seed": int(td.get("scene_seed")[0]),
                 "return": float(nxt.get("reward").sum()), "cost": float(nxt.get("cost").sum()),
                 "success": bool(nxt.get("success")[-1]), "bytes": len(data),
                 "sha256": hashlib.sha256(data).hexdigest(), **extra}
        # One small O_APPEND write cannot be torn by a process kill; fsync makes it durable.
        write_bytes(self.directory / "manifest.jsonl", (json.dumps(entry) + "\n").encode(), append=True)
        self.entries.append(entry)
        return entry

    def close(self) -> None:
        """Release the directory lock (finished episodes are already on disk)."""
        self._lock.release()

    def __enter__(self) -> DemonstrationRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def record(mentor, recorder: DemonstrationRecorder, steps: int, *, exact: bool = False, progress: bool = True,
           render_mode: str | None = None) -> dict[str, Any]:
    """Let ``mentor`` drive alone for ``steps`` env steps, one episode per next scene seed.

    Stops at the first episode boundary at or after ``steps`` (whole episodes only). With
    ``exact``, stops at exactly ``steps`` instead: the last episode is cut there and stored with
    its final step marked ``truncated`` (like a time limit). A mentor whose ``quit_requested``
    turns true (a person closing the window) ends the run the same way, keeping the episode's
    steps so far. Returns episodes, steps, seconds, steps/s, quit.
    """
    if steps < 1:
        raise ValueError(f"record: steps must be >= 1, got {steps}")
    env = make_gym_env(recorder.env_config, render_mode=render_mode)
    done_steps, episodes, start, quit_ = 0, 0, time.perf_counter(), False
    bar = tqdm(total=steps, unit="step", desc=f"record {recorder.metadata['mentor']}", disable=not progress)
    try:
        while done_steps < steps and not quit_:
            seed = recorder.next_scene_seed()
            obs, _ = env.reset(options={"scene_seed": seed})
            mentor.reset(env)
            recorder.discard_episode()
            finished = False
            while not finished and not (exact and done_steps >= steps):
                action = np.asarray(mentor.act(env), dtype=np.float32).reshape(2)
                if quit_ := bool(getattr(mentor, "quit_requested", False)):  # a person closed the window
                    break
                if not np.all(np.isfinite(action)):
                    raise ValueError(f"mentor {recorder.metadata['mentor']!r} returned a non-finite action {action}")
                action = np.clip(action, -1.0, 1.0)
                next_obs, reward, terminated, truncated, info = env.step(action)
                recorder.add_step(obs, action, next_obs, reward, terminated, truncated, info)
                obs, finished, done_steps = next_obs, terminated or truncated, done_steps + 1
                bar.update(1)
                bar.total = max(bar.total, bar.n)  # finishing the last episode overshoots ``steps``
            episodes += recorder.end_episode(cut=not finished) is not None
            bar.set_postfix(episodes=recorder.episodes)
    finally:
        bar.close()
        env.close()
    elapsed = time.perf_counter() - start
    return {"episodes": episodes, "steps": done_steps, "seconds": elapsed, "steps_per_s": done_steps / elapsed,
            "quit": quit_}


__all__ = ["DemonstrationRecorder", "dataset_info", "load_demonstrations", "read_manifest", "read_metadata", "record"]
