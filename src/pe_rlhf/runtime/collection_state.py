"""The collection in progress at a checkpoint (``single`` backend), so a resumed run takes the very next step.

A checkpoint taken between two batches holds networks, optimisers, buffers, counters and RNG states. To
continue bit-identically the resumed run must also step from where the original was: the same episode at the
same step, the same takeover, the same scene draws after it, the same trajectory ids. :func:`capture_collection`
returns that as JSON data (the checkpoint's ``state["collection"]``):

=================  ======================================================================================
``env``            the simulator's ``DrivingEnv.resume_state``: scene RNG, scene and actions of the episode
``takeover``       ``TakeoverCore.state_dict``: takeover in progress, the selector's veto count, physics' plan
``carrier``        the collector's carrier: the tensordict the next step starts from (each leaf as
                   ``{"key", "dtype", "shape", "data"}``; root ``observation`` ``(O,)``, last step's outputs)
``traj_id``        the collector's next trajectory id (``("collector", "traj_ids")`` goes on from it)
=================  ======================================================================================

:func:`restore_collection` puts it back into a freshly built collector over the same env (replaying the
episode's actions), after the collector's own reset; the mentor's state is the checkpoint's ``mentor``,
loaded again after that reset. Multi-worker backends own their envs in the workers: nothing is captured
(``None``) and a resumed run starts a fresh episode there.

The carrier is TorchRL's ``Collector._carrier`` (documented in ``Collector.rollout``); no public API sets it.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector

from pe_rlhf.transforms import InterventionTransform


def capture_collection(collector, transform: InterventionTransform | None) -> dict | None:
    """The collection state of ``collector`` (call between batches), or None when it cannot be captured (a
    multi-worker collector, or no ``InterventionTransform`` in this process)."""
    if not isinstance(collector, Collector) or transform is None:
        return None
    sim = transform.driving_env
    if not hasattr(sim, "resume_state"):
        return None
    traj_pool = collector.state_dict().get("traj_pool")
    return {"env": sim.resume_state(), "takeover": transform.core.state_dict(sim),
            "carrier": encode_tensordict(collector._carrier),
            "traj_id": None if traj_pool is None else int(traj_pool["traj_id"])}


def restore_collection(collector, transform: InterventionTransform, state: dict, mentor_state: dict | None) -> None:
    """Put :func:`capture_collection`'s ``state`` back: replay the episode, restore the takeover, the mentor
    (``mentor_state``: the checkpoint's), the carrier and the trajectory ids. Global RNGs are not touched
    by this call beyond what the replayed simulator steps use (none: a scene's traffic has its own)."""
    transform.driving_env.load_resume_state(state["env"])
    transform.core.load_state_dict(state["takeover"])
    if mentor_state is not None:
        transform.mentor.load_state_dict(mentor_state)
    if state.get("traj_id") is not None:
        fresh = collector.state_dict()
        # load_state_dict draws one id for the carrier it keeps: the one before the saved next id
        collector.load_state_dict({"frames": fresh["frames"], "iter": fresh["iter"],
                                   "traj_pool": {"traj_id": torch.tensor(int(state["traj_id"]) - 1, dtype=torch.int)}},
                                  strict=False)
    carrier = decode_tensordict(state["carrier"], collector._carrier.batch_size)
    collector._carrier = carrier.to(collector._carrier.device) if collector._carrier.device is not None else carrier


def encode_tensordict(td: TensorDictBase) -> list[dict]:
    """Every tensor leaf of ``td`` as JSON data (``key``: list of names, ``dtype``, ``shape``, ``data`` flat);
    exact for bool, integer and float32/float64 leaves."""
    out = []
    for key, value in td.items(include_nested=True, leaves_only=True):
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"carrier entry {key!r} is a {type(value).__name__}, not a tensor")
        key = [key] if isinstance(key, str) else list(key)
        out.append({"key": key, "dtype": str(value.dtype).removeprefix("torch."), "shape": list(value.shape),
                    "data": value.detach().cpu().reshape(-1).tolist()})
    return out


def decode_tensordict(leaves: list[dict], batch_size) -> TensorDict:
    """The tensordict :func:`encode_tensordict` encoded (on the CPU, no device)."""
    td = TensorDict({}, batch_size=batch_size)
    for leaf in leaves:
        value = torch.tensor(leaf["data"], dtype=getattr(torch, leaf["dtype"])).reshape(leaf["shape"])
        td.set(tuple(leaf["key"]), value)
    return td


__all__ = ["capture_collection", "decode_tensordict", "encode_tensordict", "restore_collection"]
