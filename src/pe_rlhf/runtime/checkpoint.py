"""Crash-safe training checkpoints: modules, optimizers, replay buffers, RNG states and run state.

On disk (``directory/``)::

    ckpt_000012000/            one complete checkpoint (``ckpt_{step:09d}``)
        tensors.pt             torch.save({"format_version", "modules": {name: state_dict},
                               "optimizers": {name: state_dict}}); plain tensors/ints/floats/
                               strings/lists/tuples/dicts only, loaded with ``weights_only=True``
        state.json             the caller's JSON state (counters, mentor, schedule, config, the collection in
                               progress: :mod:`pe_rlhf.runtime.collection_state`)
        rng.pt                 torch CPU (+ CUDA) generator states as uint8 tensors, numpy's
                               global MT19937 state and Python ``random``'s state as lists of ints
                               (``weights_only=True`` as well)
        buffer_<name>/         ``TensorDictReplayBuffer.dumps`` (memmap + JSON files) of the filled rows only
                               (:func:`~pe_rlhf.runtime.buffer_rows.filled_rows_only`: the size of what was
                               collected, not of the buffer's capacity)
        COMPLETE               JSON written last: format_version, step, ``sha256`` of tensors.pt,
                               and bytes + sha256 of every other file in the checkpoint
    latest                     the newest checkpoint's directory name (one line)
    .lock                      held (:class:`~pe_rlhf.filelock.FileLock`) while a checkpoint is written

Writing: everything goes to ``.tmp-ckpt_{step:09d}-{pid}/`` (each file fsync'd), ``COMPLETE`` last,
then the directory is renamed to ``ckpt_{step:09d}`` (an atomic rename), the parent fsync'd, and
``latest`` replaced atomically; only then are checkpoints beyond ``keep`` deleted. A failed write
(disk full, ...) removes its temp directory and raises an ``OSError`` (same errno) saying which
checkpoint is still intact; leftover temp directories of a killed writer are ignored by loaders and
removed by the next save.

Loading: ``latest`` names the checkpoint; if it is missing, malformed or points to a directory
without ``COMPLETE``, the newest directory with ``COMPLETE`` is used (with a warning). The marker's
checksums are verified, tensors are read with ``torch.load(weights_only=True)``, pickles in buffer
directories are refused unless they hold only plain data (no globals, no reduce), so a tampered
checkpoint cannot run code; every corrupt or unsafe file raises :class:`CheckpointError` naming it.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import pickletools
import random
import re
import shutil
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from pe_rlhf import durable
from pe_rlhf.filelock import FileLock
from pe_rlhf.runtime.buffer_rows import filled_rows_only

__all__ = [
    "CheckpointMismatch",
    "CheckpointError",
    "FORMAT_VERSION",
    "capture_rng",
    "find_checkpoint",
    "list_checkpoints",
    "load_checkpoint",
    "restore_rng",
    "save_checkpoint",
]

FORMAT_VERSION = 1
TENSORS, STATE, RNG, MARKER, LATEST = "tensors.pt", "state.json", "rng.pt", "COMPLETE", "latest"
BUFFER_PREFIX = "buffer_"
CKPT_NAME = re.compile(r"^ckpt_(\d{9,})$")
TMP_PREFIX = ".tmp-ckpt_"
OLD_PREFIX = ".old-ckpt_"
BUFFER_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
# Pickle opcodes that import or call something: a pickle without them can only build plain data.
_CODE_OPCODES = frozenset({"GLOBAL", "STACK_GLOBAL", "REDUCE", "INST", "OBJ", "NEWOBJ", "NEWOBJ_EX",
                           "BUILD", "EXT1", "EXT2", "EXT4", "PERSID", "BINPERSID"})


class CheckpointError(ValueError):
    """A checkpoint file is truncated, corrupt, unsafe or in an unknown format (the message names it)."""


class CheckpointMismatch(ValueError):
    """The objects given to :func:`load_checkpoint` are not those the checkpoint holds: ``kind`` (modules,
    optimizers, replay buffers), the names ``missing`` from the checkpoint and those ``extra`` in it."""

    def __init__(self, message: str, kind: str, missing: list[str], extra: list[str]):
        super().__init__(message)
        self.kind, self.missing, self.extra = kind, missing, extra


# --------------------------------------------------------------------------- RNG states


def capture_rng() -> dict[str, Any]:
    """Torch (CPU, and CUDA when initialised), numpy's global and Python ``random``'s RNG states.

    Only tensors, ints, floats and lists: ``torch.save``-able and loadable with ``weights_only=True``.
    """
    version, internal, gauss_next = random.getstate()
    name, key, pos, has_gauss, cached = np.random.get_state(legacy=True)
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {"bit_generator": str(name), "key": [int(k) for k in key], "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "python": {"version": int(version), "internal": [int(i) for i in internal],
                   "gauss_next": None if gauss_next is None else float(gauss_next)},
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = list(torch.cuda.get_rng_state_all())
    return state


def restore_rng(state: Mapping[str, Any]) -> None:
    """Restore what :func:`capture_rng` returned (ValueError if it is malformed).

    CUDA states are restored for as many devices as both the saved state and this machine have.
    """
    try:
        torch_state = state["torch"]
        if not (isinstance(torch_state, torch.Tensor) and torch_state.dtype == torch.uint8):
            raise TypeError(f"torch state must be a uint8 tensor, got {type(torch_state).__name__}")
        np_state = state["numpy"]
        np_tuple = (str(np_state["bit_generator"]), np.asarray(np_state["key"], dtype=np.uint32),
                    int(np_state["pos"]), int(np_state["has_gauss"]), float(np_state["cached_gaussian"]))
        if np_tuple[1].shape != (624,):
            raise ValueError(f"numpy MT19937 key has shape {np_tuple[1].shape}, expected (624,)")
        py = state["python"]
        gauss = py["gauss_next"]
        py_tuple = (int(py["version"]), tuple(int(i) for i in py["internal"]),
                    None if gauss is None else float(gauss))
        cuda = state.get("cuda") or []
        # validate everything before touching any generator
        probe = random.Random()
        probe.setstate(py_tuple)
        np.random.RandomState().set_state(np_tuple)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"malformed RNG state: {type(e).__name__}: {e}") from None
    torch.set_rng_state(torch_state.cpu())
    np.random.set_state(np_tuple)
    random.setstate(py_tuple)
    if cuda and torch.cuda.is_available():
        for device, cuda_state in enumerate(cuda[: torch.cuda.device_count()]):
            torch.cuda.set_rng_state(cuda_state.cpu(), device)


# --------------------------------------------------------------------------- small file helpers


def _rmtree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def _step_of(path: Path) -> int | None:
    m = CKPT_NAME.match(path.name)
    return int(m.group(1)) if m else None


def _dir_name(step: int) -> str:
    return f"ckpt_{step:09d}"


# --------------------------------------------------------------------------- validation helpers


_PLAIN = (str, int, float, bool, type(None), torch.dtype, torch.device, torch.Size)


def _check_weights_only(obj: Any, where: str) -> None:
    """TypeError naming ``where`` unless ``obj`` is what ``torch.load(weights_only=True)`` rebuilds."""
    if isinstance(obj, torch.Tensor):
        if type(obj) not in (torch.Tensor, torch.nn.Parameter):
            raise TypeError(f"{where} is a {type(obj).__name__} (a tensor subclass): not weights_only-loadable")
    elif isinstance(obj, Mapping):
        if not isinstance(obj, dict):
            raise TypeError(f"{where} is a {type(obj).__name__}, not a dict")
        for k, v in obj.items():
            if not isinstance(k, (str, int)):
                raise TypeError(f"{where} has a key of type {type(k).__name__}: {k!r}")
            _check_weights_only(v, f"{where}[{k!r}]")
    elif isinstance(obj, (list, tuple)) and type(obj) in (list, tuple):
        for i, v in enumerate(obj):
            _check_weights_only(v, f"{where}[{i}]")
    elif not isinstance(obj, _PLAIN):
        raise TypeError(f"{where} is a {type(obj).__name__}: checkpoints hold only tensors, numbers, "
                        "strings and lists/tuples/dicts of them (loadable with weights_only=True)")


def _jsonable(obj: Any, where: str) -> Any:
    """``obj`` with numpy scalars made Python numbers; TypeError naming ``where`` for anything JSON
    would not round-trip (objects, non-string keys)."""
    if isinstance(obj, (str, bool, int, float, type(None))):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise TypeError(f"state{where} has a non-string key {k!r} (JSON would turn it into a string)")
            out[k] = _jsonable(v, f"{where}[{k!r}]")
        return out
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    raise TypeError(f"state{where} is a {type(obj).__name__}: the checkpoint state must be JSON-serialisable "
                    "(convert arrays/tensors with .tolist(), objects with their state_dict())")


def _pickle_is_plain(data: bytes) -> bool:
    """True iff ``data`` is one well-formed pickle that imports and calls nothing."""
    try:
        ops = list(pickletools.genops(data))
    except Exception:  # noqa: BLE001 - malformed stream
        return False
    if not ops or ops[-1][0].name != "STOP" or ops[-1][2] + 1 != len(data):
        return False
    return not any(op.name in _CODE_OPCODES for op, _, _ in ops)


def short_error(e: BaseException, limit: int = 300) -> str:
    """``e`` in one line of at most ``limit`` characters (torch's weights_only refusal: its reason only)."""
    text = " ".join(str(e).split())
    # torch's weights_only refusal is a page of advice to load unsafely; keep only its reason
    m = re.search(r"WeightsUnpickler error: (.*?)(?: was not an allowed global| Check the recommended| We intend|$)",
                  text)
    if m:
        return f"the file is not plain tensor data ({m.group(1).strip()[:160]})"
    return f"{type(e).__name__}: {text[:limit]}{'...' if len(text) > limit else ''}"


# --------------------------------------------------------------------------- buffers


def _buffer_is_empty(buffer) -> bool:
    """Nothing to save: no rows, or a lazy storage never written (a buffer of buffers answers ``len`` only)."""
    return len(buffer) == 0 or not getattr(getattr(buffer, "_storage", None), "initialized", True)


def _sanitize_prefetch(buffer_dir: Path, buffer) -> None:
    """torchrl pickles the prefetch queue (``prefetch.pkl``); a queue of sampled batches needs globals
    and would be refused at load time, so the file is rewritten as an empty queue of the buffer's
    capacity (the resumed buffer samples those batches afresh). The file is never unpickled here:
    it is recognised as plain data by :func:`_pickle_is_plain` or replaced outright."""
    path = buffer_dir / "prefetch.pkl"
    if not path.exists() or _pickle_is_plain(path.read_bytes()):
        return
    import pickle

    state = {"version": 1, "capacity": int(getattr(buffer, "_prefetch_cap", 0) or 0), "queue": ()}
    warnings.warn(f"{buffer_dir.name}: the replay buffer's prefetched batches are not checkpointed; "
                  "a resumed buffer samples them anew", stacklevel=3)
    path.unlink()
    durable.write_bytes(path, pickle.dumps(state, protocol=4))


def _check_buffer_files(buffer_dir: Path) -> None:
    """Refuse files in a buffer directory that torchrl would unpickle unless they are plain data."""
    for path in sorted(p for p in buffer_dir.rglob("*") if p.is_file()):
        if path.suffix in (".memmap", ".json") or path.name.endswith(".memmap.zlib"):  # raw data, never unpickled
            continue
        data = path.read_bytes()
        if data[:2] == b"PK":  # a torch zip archive (torchrl loads it with torch.load)
            try:
                torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
            except Exception as e:  # noqa: BLE001
                raise CheckpointError(f"refusing {path}: not loadable with weights_only=True "
                                      f"({short_error(e, 160)})") from None
        elif not _pickle_is_plain(data):
            raise CheckpointError(f"refusing {path}: a pickle that imports or calls code (or is not a "
                                  "well-formed pickle) cannot be loaded safely")


# --------------------------------------------------------------------------- save


def _manifest_entry(path: Path) -> dict[str, Any]:
    return {"bytes": path.stat().st_size, "sha256": durable.sha256_file(path)}


def _prune(directory: Path, newest: Path, keep: int) -> None:
    others = [p for p in list_checkpoints(directory) if p != newest]
    for old in others[: max(len(others) - (keep - 1), 0)]:  # list is oldest first
        _rmtree(old)


def save_checkpoint(
    directory: str | os.PathLike,
    *,
    step: int,
    modules: Mapping[str, torch.nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
    replay_buffers: Mapping[str, Any] | None = None,
    state: Mapping[str, Any] | None = None,
    keep: int = 2,
) -> Path:
    """Write a complete checkpoint for ``step`` under ``directory`` and return its path.

    ``state`` is JSON-serialisable run state (counters, mentor/schedule state, config); numpy
    scalars are converted, anything else that JSON would not round-trip raises TypeError. A key
    ``"step"`` in it must equal ``step``. ``keep`` (>= 1) complete checkpoints remain afterwards
    (the new one and the newest others by step). Saving a step that already exists replaces it.

    Raises TypeError/ValueError for bad arguments (nothing is written), and ``OSError`` (errno kept)
    if writing fails; then the previous checkpoints and ``latest`` are left as they were.
    """
    directory = Path(directory)
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 0:
        raise ValueError(f"step={step!r}: must be an int >= 0")
    step = int(step)
    if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
        raise ValueError(f"keep={keep!r}: must be an int >= 1")
    state = dict(state or {})
    if "step" in state and state["step"] != step:
        raise ValueError(f"state['step']={state['step']!r} differs from step={step}")
    replay_buffers = dict(replay_buffers or {})
    for name in replay_buffers:
        if not isinstance(name, str) or not BUFFER_NAME.match(name):
            raise ValueError(f"replay buffer name {name!r}: use letters, digits, '_', '.', '-'")
    for kind, objs in (("modules", modules), ("optimizers", optimizers)):
        for name in objs:
            if not isinstance(name, str):
                raise ValueError(f"{kind} name {name!r} must be a string")

    # Everything captured in memory first (RNG before anything could draw from it).
    rng_state = capture_rng()
    json_state = _jsonable(state, "")
    state_bytes = json.dumps(json_state, indent=1, sort_keys=True).encode()
    payload = {
        "format_version": FORMAT_VERSION,
        "modules": {name: m.state_dict() for name, m in modules.items()},
        "optimizers": {name: o.state_dict() for name, o in optimizers.items()},
    }
    _check_weights_only(payload, "checkpoint")
    _check_weights_only(rng_state, "rng")
    buf = io.BytesIO()
    torch.save(payload, buf)
    tensors_bytes = buf.getvalue()
    buf = io.BytesIO()
    torch.save(rng_state, buf)
    rng_bytes = buf.getvalue()

    directory.mkdir(parents=True, exist_ok=True)
    final = directory / _dir_name(step)
    with FileLock(directory / ".lock"):
        for stale in list(directory.iterdir()):  # leftovers of writers that died (we hold the lock)
            if not stale.is_dir():
                continue
            if stale.name.startswith(OLD_PREFIX):  # died while replacing a step: put it back if needed
                m = re.match(r"^\.old-(ckpt_\d{9,})-\d+$", stale.name)
                original = directory / (m.group(1) if m else "-")
                if m and not original.exists() and (stale / MARKER).is_file():
                    os.rename(stale, original)
                    continue
            if stale.name.startswith((TMP_PREFIX, OLD_PREFIX)):
                _rmtree(stale)
        previous = find_checkpoint(directory)
        tmp = directory / f"{TMP_PREFIX}{step:09d}-{os.getpid()}"
        old, renamed, published = None, False, False
        try:
            tmp.mkdir()
            durable.write_bytes(tmp / TENSORS, tensors_bytes)
            durable.write_bytes(tmp / STATE, state_bytes)
            durable.write_bytes(tmp / RNG, rng_bytes)
            buffers_meta = {}
            for name, buffer in replay_buffers.items():
                if _buffer_is_empty(buffer):
                    buffers_meta[name] = {"empty": True}
                    continue
                bdir = tmp / f"{BUFFER_PREFIX}{name}"
                with filled_rows_only(buffer):  # the rows collected, not the capacity's uninitialised rest
                    buffer.dumps(bdir)
                _sanitize_prefetch(bdir, buffer)
                buffers_meta[name] = {"empty": False, "length": len(buffer)}
            files = {}
            for path in sorted(p for p in tmp.rglob("*") if p.is_file()):
                rel = path.relative_to(tmp).as_posix()
                if rel == TENSORS:
                    files[rel] = {"bytes": len(tensors_bytes), "sha256": hashlib.sha256(tensors_bytes).hexdigest()}
                    continue
                durable.fsync_path(path)
                files[rel] = _manifest_entry(path)
            for sub in sorted(p for p in tmp.rglob("*") if p.is_dir()):
                durable.fsync_path(sub)
            marker = {
                "format_version": FORMAT_VERSION,
                "step": step,
                "sha256": files[TENSORS]["sha256"],
                "modules": sorted(payload["modules"]),
                "optimizers": sorted(payload["optimizers"]),
                "buffers": buffers_meta,
                "files": files,
                "torch": torch.__version__,
            }
            durable.write_bytes(tmp / MARKER, json.dumps(marker, indent=1, sort_keys=True).encode())
            durable.fsync_path(tmp)
            if final.exists():  # re-saving a step: move the old one aside, swap, then delete it
                old = directory / f"{OLD_PREFIX}{step:09d}-{os.getpid()}"
                os.rename(final, old)
            os.rename(tmp, final)
            renamed = True
            durable.fsync_path(directory)
            durable.replace_bytes(directory / LATEST, f"{final.name}\n".encode())
            published = True
            if old is not None:
                _rmtree(old)
        except BaseException as e:
            if published:  # interrupted while deleting the replaced copy: the new one stands
                raise
            _rmtree(tmp)
            if renamed:  # ``latest`` could not be updated: withdraw the new checkpoint
                _rmtree(final)
            if old is not None and old.exists() and not final.exists():
                os.rename(old, final)  # put the replaced checkpoint back
            if isinstance(e, OSError):
                kept = f"{previous.name} is intact" if previous is not None else "no earlier checkpoint exists"
                reason = e.strerror or str(e) or type(e).__name__
                raise OSError(e.errno or errno.EIO,
                              f"could not write checkpoint step {step} to {directory}: {reason} "
                              f"({e.filename or 'during the write'}); {kept}") from e
            raise
        _prune(directory, final, keep)
    return final


# --------------------------------------------------------------------------- find / load


def list_checkpoints(directory: str | os.PathLike) -> list[Path]:
    """The complete checkpoints (with ``COMPLETE``) under ``directory``, oldest step first."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    found = [p for p in directory.iterdir() if _step_of(p) is not None and (p / MARKER).is_file()]
    return sorted(found, key=_step_of)


def find_checkpoint(directory: str | os.PathLike) -> Path | None:
    """The checkpoint ``load_checkpoint(directory)`` would read: ``directory`` itself if it is one,
    else the one ``latest`` names, else the newest complete one; None if there is none."""
    directory = Path(directory)
    if (directory / MARKER).is_file() and _step_of(directory) is not None:
        return directory
    complete = list_checkpoints(directory)
    latest = directory / LATEST
    if latest.is_file():
        try:
            name = latest.read_text().strip()
        except (OSError, UnicodeDecodeError):
            name = ""
        if CKPT_NAME.match(name) and (directory / name / MARKER).is_file():
            return directory / name
        if complete:
            warnings.warn(f"{latest} names {name[:60]!r}, which is not a complete checkpoint; "
                          f"using the newest complete one, {complete[-1].name}", stacklevel=2)
    return complete[-1] if complete else None


def _read_marker(ckpt: Path) -> dict[str, Any]:
    path = ckpt / MARKER
    try:
        marker = json.loads(path.read_bytes())
        if not isinstance(marker, dict):
            raise ValueError("not a JSON object")
        for key in ("format_version", "step", "sha256", "files", "buffers"):
            marker[key]  # noqa: B018 - required
        if not isinstance(marker["files"], dict) or TENSORS not in marker["files"]:
            raise ValueError(f"no entry for {TENSORS}")
    except (ValueError, KeyError, TypeError) as e:  # JSONDecodeError/UnicodeDecodeError are ValueErrors
        raise CheckpointError(f"corrupt checkpoint marker {path}: {short_error(e)}") from None
    if marker["format_version"] != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format_version {marker['format_version']!r}; this "
                              f"pe_rlhf reads version {FORMAT_VERSION}")
    if marker["sha256"] != marker["files"][TENSORS].get("sha256"):
        raise CheckpointError(f"corrupt checkpoint marker {path}: its two {TENSORS} checksums differ")
    return marker


def _verify_files(ckpt: Path, marker: dict[str, Any]) -> None:
    listed = marker["files"]
    for rel, entry in listed.items():
        path = ckpt / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            raise CheckpointError(f"corrupt checkpoint marker {ckpt / MARKER}: bad file name {rel!r}")
        if not path.is_file():
            raise CheckpointError(f"checkpoint file {path} is missing")
        size = path.stat().st_size
        if size != entry.get("bytes"):
            raise CheckpointError(f"checkpoint file {path} is truncated or corrupt: {size} bytes, "
                                  f"{MARKER} says {entry.get('bytes')}")
        if durable.sha256_file(path) != entry.get("sha256"):
            raise CheckpointError(f"checkpoint file {path} is corrupt: its sha256 differs from {MARKER}'s")
    for bdir in ckpt.glob(f"{BUFFER_PREFIX}*"):  # torchrl would read unlisted files too
        for path in bdir.rglob("*"):
            if path.is_file() and path.relative_to(ckpt).as_posix() not in listed:
                raise CheckpointError(f"unexpected file {path} (not listed in {MARKER})")


def _torch_load(path: Path) -> Any:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - unpickling errors of every kind: name the file, no stack
        raise CheckpointError(f"unreadable checkpoint file {path} (refused by torch.load(weights_only=True)): "
                              f"{short_error(e)}") from None


def _check_names(kind: str, requested: Mapping[str, Any], saved: Mapping[str, Any] | list, strict: bool,
                 ckpt: Path) -> None:
    missing = sorted(set(requested) - set(saved))
    extra = sorted(set(saved) - set(requested))
    if missing or (strict and extra):
        raise CheckpointMismatch(f"checkpoint {ckpt} {kind} mismatch: not in the checkpoint {missing}, "
                                 f"in the checkpoint but not given {extra}"
                                 + (" (strict=False loads a subset)" if extra and not missing else ""),
                                 kind, missing, extra)


def _check_module(name: str, module: torch.nn.Module, saved: Any) -> None:
    if not isinstance(saved, dict):
        raise CheckpointError(f"{TENSORS}: module {name!r} state is a {type(saved).__name__}, not a dict")
    own = module.state_dict()
    missing = [k for k in own if k not in saved]
    unexpected = [k for k in saved if k not in own]
    if missing or unexpected:
        raise ValueError(f"module {name!r} does not match the checkpoint: missing keys {missing[:5]}"
                         f"{'...' if len(missing) > 5 else ''}, unexpected keys {unexpected[:5]}"
                         f"{'...' if len(unexpected) > 5 else ''}")
    for key, value in own.items():
        other = saved[key]
        if isinstance(value, torch.Tensor):
            if not isinstance(other, torch.Tensor):
                raise ValueError(f"module {name!r} key {key!r}: checkpoint holds a {type(other).__name__}")
            if other.shape != value.shape:
                raise ValueError(f"module {name!r} key {key!r}: checkpoint shape {tuple(other.shape)}, "
                                 f"module shape {tuple(value.shape)}")


def _check_optimizer(name: str, optimizer: torch.optim.Optimizer, saved: Any) -> None:
    if not isinstance(saved, dict) or not isinstance(saved.get("param_groups"), list) \
            or not isinstance(saved.get("state"), dict):
        raise CheckpointError(f"{TENSORS}: optimizer {name!r} state is malformed")
    own = optimizer.param_groups
    sizes = [len(g["params"]) for g in own]
    saved_sizes = [len(g.get("params", ())) for g in saved["param_groups"]]
    if sizes != saved_sizes:
        raise ValueError(f"optimizer {name!r} does not match the checkpoint: parameter groups of sizes "
                         f"{sizes}, checkpoint {saved_sizes}")
    for i, (group, saved_group) in enumerate(zip(own, saved["param_groups"])):
        for j, p in zip(saved_group["params"], group["params"]):
            entry = saved["state"].get(j, {})
            for key, value in entry.items():
                if isinstance(value, torch.Tensor) and value.dim() == p.dim() and value.dim() > 0 \
                        and value.shape != p.shape:
                    raise ValueError(f"optimizer {name!r} group {i} state {key!r}: checkpoint shape "
                                     f"{tuple(value.shape)}, parameter shape {tuple(p.shape)}")


def load_checkpoint(
    directory: str | os.PathLike,
    *,
    modules: Mapping[str, torch.nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
    replay_buffers: Mapping[str, Any] | None = None,
    strict: bool = True,
    restore_rng_state: bool = True,
) -> dict[str, Any]:
    """Restore the newest checkpoint under ``directory`` (or ``directory`` itself if it is a
    checkpoint) into the given objects; return its ``state`` with ``"step"`` added.

    ``strict`` (default): the names given must be exactly those saved; ``strict=False`` loads a
    subset (e.g. only the modules, for evaluation). Within a module keys and shapes must match.

    Raises FileNotFoundError if there is no checkpoint, :class:`CheckpointError` (a ValueError) for
    a corrupt, truncated or unsafe file (named in the message), ValueError for a mismatch between
    the checkpoint and the objects. Everything is verified before any object is modified.
    """
    directory = Path(directory)
    ckpt = find_checkpoint(directory)
    if ckpt is None:
        raise FileNotFoundError(f"no complete checkpoint under {directory}")
    replay_buffers = dict(replay_buffers or {})
    marker = _read_marker(ckpt)
    try:
        step = int(marker["step"])
    except (TypeError, ValueError):
        raise CheckpointError(f"corrupt checkpoint marker {ckpt / MARKER}: step {marker['step']!r}") from None
    _verify_files(ckpt, marker)
    later = [p.name for p in list_checkpoints(ckpt.parent) if _step_of(p) > step]
    if later:
        warnings.warn(f"loading {ckpt.name}, but {later} have larger steps", stacklevel=2)

    payload = _torch_load(ckpt / TENSORS)
    if not isinstance(payload, dict) or not isinstance(payload.get("modules"), dict) \
            or not isinstance(payload.get("optimizers"), dict):
        raise CheckpointError(f"{ckpt / TENSORS} does not hold a checkpoint payload")
    rng_state = _torch_load(ckpt / RNG) if restore_rng_state else None
    try:
        state = json.loads((ckpt / STATE).read_bytes())
        if not isinstance(state, dict):
            raise ValueError("not a JSON object")
    except ValueError as e:
        raise CheckpointError(f"corrupt checkpoint state {ckpt / STATE}: {short_error(e)}") from None

    _check_names("modules", modules, payload["modules"], strict, ckpt)
    _check_names("optimizers", optimizers, payload["optimizers"], strict, ckpt)
    _check_names("replay buffers", replay_buffers, marker["buffers"], strict, ckpt)
    for name, module in modules.items():
        _check_module(name, module, payload["modules"][name])
    for name, optimizer in optimizers.items():
        _check_optimizer(name, optimizer, payload["optimizers"][name])
    for name in replay_buffers:
        if not marker["buffers"][name].get("empty"):
            bdir = ckpt / f"{BUFFER_PREFIX}{name}"
            if not bdir.is_dir():
                raise CheckpointError(f"checkpoint buffer directory {bdir} is missing")
            _check_buffer_files(bdir)

    for name, module in modules.items():
        try:
            module.load_state_dict(payload["modules"][name], strict=True)
        except RuntimeError as e:
            raise ValueError(f"module {name!r} could not load the checkpoint: {short_error(e)}") from None
    for name, optimizer in optimizers.items():
        try:
            optimizer.load_state_dict(payload["optimizers"][name])
        except (ValueError, KeyError, RuntimeError) as e:
            raise ValueError(f"optimizer {name!r} could not load the checkpoint: {short_error(e)}") from None
    for name, buffer in replay_buffers.items():
        if marker["buffers"][name].get("empty"):
            buffer.empty()
            continue
        bdir = ckpt / f"{BUFFER_PREFIX}{name}"
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", FutureWarning)  # tensordict's allow_pickle notice
                with filled_rows_only(buffer):
                    buffer.loads(bdir)
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(f"replay buffer {name!r} could not be loaded from {bdir}: {short_error(e)}") from None
        expected = marker["buffers"][name].get("length")
        if expected is not None and len(buffer) != expected:
            raise CheckpointError(f"replay buffer {name!r} from {bdir} holds {len(buffer)} items, "
                                  f"{MARKER} says {expected}")
    if rng_state is not None:
        try:
            restore_rng(rng_state)
        except ValueError as e:
            raise CheckpointError(f"{ckpt / RNG}: {e}") from None
    state["step"] = step
    return state
