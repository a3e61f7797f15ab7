"""Issue 45, case 6: every output is written atomically and never through a symlink that leaves the run folder.

Before: ``Run.finish`` saved ``actor.pt`` with ``torch.save`` straight to its path, so an ``actor.pt`` linked to a
file outside the run folder had that file overwritten on ``--resume``.
"""

from __future__ import annotations

import pytest
from _runs import train

from pe_rlhf.runtime.config_rules import ConfigError

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("links") / "run"
    train(out, "collector.total_frames=100")
    return out


@pytest.mark.parametrize("name", ["actor.safetensors", "final_eval.json", "metrics.csv", "checkpoints/latest"])
def test_a_symlink_out_of_the_run_folder_is_refused_and_its_target_untouched(finished, tmp_path, name):
    outside = tmp_path / f"precious-{name.replace('/', '-')}"
    outside.write_bytes(b"a person's file")
    original = (finished / name).read_bytes()
    (finished / name).unlink()
    (finished / name).symlink_to(outside)
    try:
        with pytest.raises(ConfigError, match=f"{name} is a symlink to .*outside the run folder"):
            train(finished, "collector.total_frames=100", resume=True)
    finally:
        (finished / name).unlink()
        (finished / name).write_bytes(original)
    assert outside.read_bytes() == b"a person's file"


def test_a_symlink_inside_the_run_folder_is_replaced_not_written_through(finished):
    kept = finished / "kept-actor.safetensors"
    kept.write_bytes(b"an earlier actor")
    (finished / "actor.safetensors").unlink()
    (finished / "actor.safetensors").symlink_to(kept)
    train(finished, "collector.total_frames=100", resume=True)
    assert kept.read_bytes() == b"an earlier actor"
    assert not (finished / "actor.safetensors").is_symlink() and (finished / "actor.safetensors").stat().st_size > 1000
