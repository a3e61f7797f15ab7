"""``TakeoverBalancedReplayBuffer`` (``replay_buffer.takeover_share``): takeover rows apart, their share of a batch,
checkpoints, and the recipe with it."""

from __future__ import annotations

import pytest
import torch
from _scripts import load_pe_rlhf_recipe
from tensordict import TensorDict

from pe_rlhf.runtime.checkpoint import find_checkpoint, load_checkpoint, save_checkpoint
from pe_rlhf.algorithms.proxy_q.builders import build_replay_buffer
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.takeover_replay import TakeoverBalancedReplayBuffer


def rows(n: int, takeover: bool, start: int = 0) -> TensorDict:
    """``n`` rows numbered from ``start`` (``obs``), all takeover rows or none."""
    return TensorDict({"obs": torch.arange(start, start + n, dtype=torch.float32).unsqueeze(-1),
                       "next": {"intervention": torch.full((n, 1), takeover)}}, batch_size=[n])


def test_rows_go_to_their_buffer_and_a_batch_holds_the_share():
    torch.manual_seed(0)
    buffer = TakeoverBalancedReplayBuffer(size=100, batch_size=8, takeover_share=0.5)
    mixed = torch.cat([rows(5, True), rows(20, False, start=100)])
    buffer.extend(mixed[torch.randperm(25)])
    assert (len(buffer.takeover), len(buffer.agent), len(buffer)) == (5, 20, 25)
    assert buffer.split() == (4, 4)
    batch = buffer.sample()
    assert batch.shape == (8,)
    assert batch["next", "intervention"].reshape(-1).tolist() == [True] * 4 + [False] * 4
    assert (batch["obs"][:4] < 100).all() and (batch["obs"][4:] >= 100).all()


def test_few_takeover_rows_fill_what_they_can_and_an_empty_agent_buffer_gives_all_to_takeovers():
    buffer = TakeoverBalancedReplayBuffer(size=100, batch_size=10, takeover_share=0.5)
    buffer.extend(rows(3, True))
    assert buffer.split() == (10, 0)  # the agent has no rows yet (the warm-up)
    assert buffer.sample()["next", "intervention"].all()
    buffer.extend(rows(30, False, start=100))
    assert buffer.split() == (3, 7)  # min(half of 10, 3 stored)
    assert TakeoverBalancedReplayBuffer(100, 10, takeover_share=0.0).split() == (10, 0)  # nothing stored at all
    with pytest.raises(RuntimeError, match="empty"):
        TakeoverBalancedReplayBuffer(100, 10).sample()
    with pytest.raises(ValueError, match=r"takeover_share=1.5 is invalid: a share in \[0, 1\]"):
        TakeoverBalancedReplayBuffer(100, 10, takeover_share=1.5)


def test_the_share_is_a_recipe_field_and_null_keeps_one_uniform_buffer():
    # PE-RLHF's default is 0.5 since issue 41 (the authors' code and PVP); null (recipes/haco's) keeps one buffer
    cfg = load_config(overrides=["profile=smoke", "replay_buffer.takeover_share=null"])
    assert cfg.replay_buffer.takeover_share is None
    assert not isinstance(build_replay_buffer(cfg, balanced=True), TakeoverBalancedReplayBuffer)
    cfg = load_config(overrides=["profile=smoke"])
    assert cfg.replay_buffer.takeover_share == 0.5
    assert isinstance(build_replay_buffer(cfg, balanced=True), TakeoverBalancedReplayBuffer)
    assert not isinstance(build_replay_buffer(cfg), TakeoverBalancedReplayBuffer)  # the ensemble's warm-up buffer


def test_a_checkpoint_restores_both_buffers_and_the_next_batch(tmp_path):
    buffer = TakeoverBalancedReplayBuffer(size=50, batch_size=6, takeover_share=0.5)
    buffer.extend(torch.cat([rows(7, True), rows(9, False, start=100)]))
    save_checkpoint(tmp_path / "ckpt", step=1, modules={}, optimizers={}, replay_buffers={"replay": buffer})
    restored = TakeoverBalancedReplayBuffer(size=50, batch_size=6, takeover_share=0.5)
    load_checkpoint(tmp_path / "ckpt", modules={}, optimizers={}, replay_buffers={"replay": restored})
    assert (len(restored.takeover), len(restored.agent)) == (7, 9)
    for part in ("takeover", "agent"):
        assert torch.equal(getattr(restored, part)[:]["obs"], getattr(buffer, part)[:]["obs"])
    only_takeovers = TakeoverBalancedReplayBuffer(size=50, batch_size=6)
    only_takeovers.extend(rows(4, True))
    save_checkpoint(tmp_path / "ckpt2", step=1, modules={}, optimizers={}, replay_buffers={"replay": only_takeovers})
    load_checkpoint(tmp_path / "ckpt2", modules={}, optimizers={}, replay_buffers={"replay": restored})
    assert (len(restored.takeover), len(restored.agent)) == (4, 0)


def test_a_smoke_run_with_the_share_trains_and_resumes(tmp_path):
    """The recipe with ``replay_buffer.takeover_share=0.5``: the run finishes with both kinds of rows checkpointed
    apart, and a resume continues from its checkpoint."""
    out = tmp_path / "run"
    recipe = load_pe_rlhf_recipe()
    result = recipe.main(["profile=smoke", "eval.video=false", "replay_buffer.takeover_share=0.5", "--out", str(out)])
    assert (out / "actor.safetensors").exists() and "success_rate" in result
    saved = find_checkpoint(out / "checkpoints") / "buffer_replay"
    assert (saved / "takeover").is_dir() and (saved / "agent").is_dir()
    recipe.main(["--resume", str(out), "collector.total_frames=400"])
    lines = (out / "metrics.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert int(float(lines[-1].split(",")[header.index("step")])) == 400
