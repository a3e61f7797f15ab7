"""The Q-ensemble estimator of PE-RLHF: K Q-networks evaluated in one vectorised call."""

from __future__ import annotations

import json
import os
import pickle
import zipfile
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict
from tensordict.nn import EnsembleModule, TensorDictParams
from torch import nn

from pe_rlhf import durable
from pe_rlhf.modules.networks import make_qvalue

_FORMAT = "pe_rlhf.q_ensemble"
_FORMAT_VERSION = 1
SAFETENSORS = ".safetensors"  # save_q_ensemble's format by the path's suffix (else a torch file)


class QEnsemble(nn.Module):
    """K critics of the same architecture, independently initialised, run by ``vmap``.

    ``values(observation, action)`` takes ``(*B, obs_dim)`` and ``(*B, A)`` and returns
    ``(K, *B)``. As a tensordict module (``forward``) it reads ``observation`` and ``action``
    and writes ``state_action_value`` ``(K, *B, 1)`` with batch size ``(K, *B)``.

    The members' parameters live in ``self.ensemble.params_td`` with a leading ``K`` dim.
    ``config`` holds the constructor arguments (``QEnsemble(**q.config)`` rebuilds the
    architecture); ``save_q_ensemble`` / ``load_q_ensemble`` persist it with the weights.

    Target networks: ``QEnsemble(**q.config)`` + ``load_state_dict``. tensordict's ``EnsembleModule``
    keeps its ``vmap``-ed forward as an attribute bound to its object, which neither pickles nor
    deep-copies on its own; a ``QEnsemble`` pickles (and deep-copies) as ``config`` + the members'
    parameters, rebuilt on load. Through ``torch.multiprocessing`` (a collector worker's env
    factory), parameters moved to shared memory with ``share_memory()`` stay shared: the worker
    sees the main process's in-place updates.
    """

    def __init__(self, obs_dim: int, action_dim: int = 2, num_members: int = 5,
                 hidden: tuple[int, ...] = (256, 256)):
        super().__init__()
        if num_members < 1:
            raise ValueError(f"QEnsemble num_members={num_members}: must be >= 1")
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.num_members = int(num_members)
        self.hidden = tuple(int(h) for h in hidden)
        self.ensemble = EnsembleModule(make_qvalue(obs_dim, action_dim, hidden), num_copies=num_members)

    @property
    def config(self) -> dict[str, Any]:
        """Constructor arguments: ``obs_dim``, ``action_dim``, ``num_members``, ``hidden``."""
        return {"obs_dim": self.obs_dim, "action_dim": self.action_dim,
                "num_members": self.num_members, "hidden": self.hidden}

    def forward(self, tensordict):
        return self.ensemble(tensordict)

    def __reduce__(self):
        # EnsembleModule's vmapped forward is bound to its object and does not pickle: rebuild the
        # architecture from ``config`` around the members' parameters. Sent to a torch.multiprocessing
        # worker, parameters in shared memory (``share_memory()``) stay shared, so the worker sees the
        # main process's in-place updates (a fit). ``copy.deepcopy`` gets a real, independent copy.
        requires_grad = any(p.requires_grad for p in self.parameters())
        return _rebuild_q_ensemble, (self.config, self.ensemble.params_td.data, requires_grad)

    def values(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        batch = observation.shape[:-1]
        td = TensorDict({"observation": observation, "action": action}, batch_size=batch)
        return self.ensemble(td).get("state_action_value").squeeze(-1)


def _rebuild_q_ensemble(config: dict[str, Any], params: TensorDict, requires_grad: bool) -> QEnsemble:
    ensemble = QEnsemble(**config)
    ensemble.ensemble.params_td = TensorDictParams(params)  # wraps the given tensors (same storage)
    return ensemble.requires_grad_(requires_grad)


def save_q_ensemble(ensemble: QEnsemble, path: str | os.PathLike) -> None:
    """Write ``ensemble``'s weights and constructor config to ``path``: a safetensors file when ``path`` ends in
    ``.safetensors`` (the config in its metadata), else ``torch.save`` of plain tensors (on CPU), ints, strings,
    lists and dicts, which loads with ``torch.load(..., weights_only=True)``. :func:`load_q_ensemble` reads both.
    """
    if not isinstance(ensemble, QEnsemble):
        raise TypeError(f"save_q_ensemble expects a QEnsemble, got {type(ensemble).__name__}")
    cfg = ensemble.config
    payload = {
        "format": _FORMAT,
        "version": _FORMAT_VERSION,
        "config": {"obs_dim": cfg["obs_dim"], "action_dim": cfg["action_dim"],
                   "num_members": cfg["num_members"], "hidden": list(cfg["hidden"])},
        "state_dict": {k: v.detach().cpu().clone() for k, v in ensemble.state_dict().items()},
    }
    if os.fspath(path).endswith(SAFETENSORS):  # weights and a string table: nothing in it can run code
        durable.save_tensors(path, payload["state_dict"], {"format": _FORMAT, "version": str(_FORMAT_VERSION),
                                                           "config": json.dumps(payload["config"])})
        return
    torch.save(payload, os.fspath(path))


def _is_torch_file(path: str) -> bool:
    with open(path, "rb") as f:
        return f.read(2) in (b"PK", b"\x80\x02")  # a torch zip archive, or a legacy pickle


def _read_payload(path: str) -> dict:
    """What ``torch.save`` would have held, from a safetensors file :func:`save_q_ensemble` wrote."""
    tensors, meta = durable.load_tensors(path)
    try:
        config = json.loads(meta.get("config", "null"))
        version = int(meta.get("version", -1))
    except ValueError:
        config, version = None, -1
    return {"format": meta.get("format"), "version": version, "config": config, "state_dict": tensors}


def load_q_ensemble(path: str | os.PathLike, *, map_location: str | torch.device | None = "cpu",
                    obs_dim: int | None = None, action_dim: int | None = None,
                    num_members: int | None = None, hidden: tuple[int, ...] | None = None) -> QEnsemble:
    """Rebuild a ``QEnsemble`` saved by ``save_q_ensemble``.

    Loads with ``torch.load(path, weights_only=True)`` (no arbitrary pickles). Any of
    ``obs_dim``, ``action_dim``, ``num_members``, ``hidden`` that is given must match the saved
    config. A missing, truncated or foreign file, a config mismatch, or weights that do not fit
    the saved config raise ``ValueError`` naming ``path`` (``FileNotFoundError`` if absent).
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"load_q_ensemble: no such file {path!r}")
    try:
        payload = _read_payload(path) if not _is_torch_file(path) else \
            torch.load(path, map_location=map_location, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, OSError, ValueError,
            TypeError, AttributeError, KeyError, IndexError, UnicodeDecodeError) as err:
        raise ValueError(f"load_q_ensemble: {path!r} is not a readable Q-ensemble checkpoint "
                         f"(corrupt, truncated, or holds non-weights objects): {err}") from err
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise ValueError(f"load_q_ensemble: {path!r} is not a Q-ensemble checkpoint "
                         f"(missing format tag {_FORMAT!r})")
    if payload.get("version") != _FORMAT_VERSION:
        raise ValueError(f"load_q_ensemble: {path!r} has format version {payload.get('version')!r}, "
                         f"expected {_FORMAT_VERSION}")
    cfg = payload.get("config")
    state = payload.get("state_dict")
    keys = ("obs_dim", "action_dim", "num_members", "hidden")
    if not isinstance(cfg, dict) or any(k not in cfg for k in keys) or not isinstance(state, dict):
        raise ValueError(f"load_q_ensemble: {path!r} lacks a complete config {keys} or a state_dict")
    try:
        saved = {"obs_dim": int(cfg["obs_dim"]), "action_dim": int(cfg["action_dim"]),
                 "num_members": int(cfg["num_members"]), "hidden": tuple(int(h) for h in cfg["hidden"])}
    except (TypeError, ValueError) as err:
        raise ValueError(f"load_q_ensemble: {path!r} has a malformed config {cfg!r}") from err
    expected = {"obs_dim": obs_dim, "action_dim": action_dim, "num_members": num_members,
                "hidden": None if hidden is None else tuple(int(h) for h in hidden)}
    mismatch = {k: (v, saved[k]) for k, v in expected.items() if v is not None and v != saved[k]}
    if mismatch:
        detail = ", ".join(f"{k}: expected {e!r}, file has {s!r}" for k, (e, s) in mismatch.items())
        raise ValueError(f"load_q_ensemble: config mismatch in {path!r}: {detail}")
    try:
        ensemble = QEnsemble(**saved)
        ensemble.load_state_dict(state, strict=True)
    except (RuntimeError, ValueError, TypeError, KeyError) as err:
        raise ValueError(f"load_q_ensemble: weights in {path!r} do not fit its config {saved}: {err}") from err
    if map_location is not None:
        ensemble = ensemble.to(map_location)
    return ensemble


def q_ensemble_from_critics(*stacks: Mapping[str, torch.Tensor], action_dim: int = 2,
                            max_members: int | None = None) -> QEnsemble:
    """A frozen ``QEnsemble`` whose members are the critics of a trained loss (e.g. a SAC run's twin Q).

    Each of ``stacks`` maps ``make_qvalue`` parameter names (``"module.mlp.0.weight"``, ...) to tensors with
    a leading copies dim, as a TorchRL loss stores them (``qvalue_network_params``,
    ``target_qvalue_network_params``); the members are the copies of every stack in order (the authors'
    4-head "ensemble" is SAC's online twin then its target twin). ``obs_dim`` and ``hidden`` are read off
    the weights; ``max_members`` keeps only the first members (1: the "w/o ensemble" ablation). Raises
    ``ValueError`` when the stacks do not describe one architecture.
    """
    if not stacks:
        raise ValueError("q_ensemble_from_critics needs at least one stack of critic parameters")
    stacks = tuple(dict(s.items()) for s in stacks)  # plain dicts or (flattened) TensorDicts
    names = sorted(stacks[0])
    for i, stack in enumerate(stacks[1:], 1):
        if sorted(stack) != names:
            raise ValueError(f"q_ensemble_from_critics: stack {i} has parameters {sorted(stack)}, stack 0 has {names}")
    merged = {name: torch.cat([torch.as_tensor(s[name]).detach().float() for s in stacks], 0) for name in names}
    weights = sorted((n for n in names if n.endswith(".weight")), key=lambda n: int(n.split(".")[-2]))
    if not weights:
        raise ValueError(f"q_ensemble_from_critics: no weight tensors among {names}")
    in_features = merged[weights[0]].shape[-1]
    hidden = tuple(int(merged[n].shape[-2]) for n in weights[:-1])
    members = int(merged[weights[0]].shape[0])
    if max_members is not None:
        members = min(members, int(max_members))
        merged = {n: t[:members] for n, t in merged.items()}
    ensemble = QEnsemble(int(in_features) - action_dim, action_dim, members, hidden)
    state = ensemble.state_dict()  # the members live in params_td; the template module's entries stay
    try:
        for n, t in merged.items():
            key = f"ensemble.params_td.{n}"
            if key not in state or state[key].shape != t.shape:
                raise RuntimeError(f"{n}: shape {tuple(t.shape)}, expected "
                                   f"{tuple(state[key].shape) if key in state else 'no such parameter'}")
            state[key] = t
        ensemble.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise ValueError(f"q_ensemble_from_critics: the parameters do not fit a make_qvalue critic "
                         f"(obs {in_features - action_dim}, hidden {hidden}): {err}") from err
    return ensemble.requires_grad_(False)
