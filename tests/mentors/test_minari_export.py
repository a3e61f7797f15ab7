"""Demonstrations to Minari and back (real minari package, real env and driver; no mocks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

minari = pytest.importorskip("minari")

from _factories import FAST_CONFIG, DriverMentor, make_intervention_env  # noqa: E402

from pe_rlhf.apps import cli  # noqa: E402
from pe_rlhf.envs import ENV_ID, DrivingConfig  # noqa: E402
from pe_rlhf.mentors.minari_export import (  # noqa: E402
    directory_episodes,
    export_minari,
    import_minari,
    read_minari,
    write_minari,
)
from pe_rlhf.mentors.recording import (  # noqa: E402
    DemonstrationRecorder,
    load_demonstrations,
    read_manifest,
    read_metadata,
    record,
)

CONFIG = DrivingConfig(horizon=40)  # short episodes (time limit)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """Three episodes: two to the time limit, the last cut short (``cut`` in its manifest line)."""
    d = tmp_path_factory.mktemp("demo") / "driver"
    with DemonstrationRecorder(d, CONFIG, "driver", seeds=[3, 4, 5]) as rec:
        record(DriverMentor(), rec, 100, exact=True, progress=False)
    assert [e["steps"] for e in read_manifest(d)] == [40, 40, 20]
    return d


@pytest.fixture
def minari_root(tmp_path, monkeypatch) -> Path:
    root = tmp_path / "minari_datasets"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


def _flat(t: torch.Tensor) -> np.ndarray:
    a = t.numpy()
    return a.reshape(len(a)) if a.ndim == 2 and a.shape[1] == 1 else a


def test_export_is_what_minari_load_dataset_reads(recorded, minari_root):
    done = export_minari(recorded, "pe-rlhf/driver-v0")
    assert done == {"dataset_id": "pe-rlhf/driver-v0", "path": str(minari_root / "pe-rlhf/driver-v0/data"),
                    "episodes": 3, "steps": 100}
    dataset = minari.load_dataset("pe-rlhf/driver-v0")
    assert dataset.total_episodes == 3 and dataset.total_steps == 100
    metas = list(dataset.storage.get_episode_metadata(dataset.episode_indices))
    for td, ep, meta in zip(directory_episodes(recorded), dataset.iterate_episodes(), metas, strict=True):
        nxt = td["next"]
        assert np.array_equal(ep.observations, np.concatenate([td["observation"].numpy(), nxt["observation"][-1:]]))
        assert ep.observations.dtype == ep.actions.dtype == ep.rewards.dtype == np.float32
        assert np.array_equal(ep.actions, td["action"].numpy())  # the mentor's executed action
        assert np.array_equal(ep.rewards, _flat(nxt["reward"]))
        assert np.array_equal(ep.terminations, _flat(nxt["terminated"]))
        assert np.array_equal(ep.truncations, _flat(nxt["truncated"]))
        assert set(ep.infos) == {k for k in nxt.keys() if k not in ("observation", "reward", "done", "terminated",
                                                                     "truncated")}
        for key, value in ep.infos.items():
            assert len(value) == len(td) + 1  # row 0, the reset's info: not recorded but the scene seed
            assert value[0] == (td["scene_seed"][0, 0].item() if key == "scene_seed" else 0), key
            assert value.dtype == nxt[key].numpy().dtype and np.array_equal(value[1:], _flat(nxt[key])), key
        assert meta["options"]["scene_seed"] == int(td["scene_seed"][0])
    assert [bool(m["cut"]) for m in metas] == [False, False, True]
    assert dataset.storage.metadata["pe_rlhf"] == read_metadata(recorded)
    assert dataset.storage.metadata["algorithm_name"] == "driver"
    env = dataset.recover_environment()  # the recorded world, through gymnasium's registry
    assert dataset.env_spec.id == ENV_ID and env.unwrapped.world == CONFIG
    env.close()


def test_import_restores_the_directory_byte_for_byte(recorded, minari_root, tmp_path):
    export_minari(recorded, "pe-rlhf/driver-v0")
    assert import_minari("pe-rlhf/driver-v0", tmp_path / "back") == {"episodes": 3, "steps": 100}
    a, b = load_demonstrations(recorded).storage[:], load_demonstrations(tmp_path / "back").storage[:]
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
    # same chunks (sha256), same manifest fields (cut included), same mentor, seeds and world
    assert read_manifest(tmp_path / "back") == read_manifest(recorded)
    before, after = read_metadata(recorded), read_metadata(tmp_path / "back")
    assert {k: after[k] for k in ("mentor", "split", "seeds", "env_config", "observation_size")} == \
           {k: before[k] for k in ("mentor", "split", "seeds", "env_config", "observation_size")}


def test_a_path_holds_the_dataset_itself(recorded, tmp_path, monkeypatch):
    monkeypatch.delenv("MINARI_DATASETS_PATH", raising=False)
    target = tmp_path / "exports" / "driver-v1"
    assert export_minari(recorded, str(target))["path"] == str(target / "data")
    assert minari.MinariDataset(target / "data").total_steps == 100
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(target.parent))
    assert minari.load_dataset("driver-v1").total_episodes == 3
    with pytest.raises(ValueError, match="already exists"):
        export_minari(recorded, str(target))
    with pytest.raises(ValueError, match="name-vN"):
        export_minari(recorded, str(tmp_path / "no_version"))
    imported = import_minari(str(target), tmp_path / "back")  # the folder, or its data/ folder
    assert imported == import_minari(str(target / "data"), tmp_path / "back2") == {"episodes": 3, "steps": 100}


def test_takeover_flags_and_the_agents_action_become_infos(minari_root):
    """A TorchRL rollout through the intervention transform: the executed action is Minari's action, the
    agent's proposal and the takeover flags are infos, and reading back gives the rollout's ``next``."""
    env = make_intervention_env()
    torch.manual_seed(0)
    rollouts = [env.rollout(20, break_when_any_done=True) for _ in range(2)]  # random agent: takeovers
    env.close()
    assert any(bool(td["next", "intervention"].any()) for td in rollouts)
    dataset = write_minari(rollouts, "pe-rlhf/rollout-v0", env_config=DrivingConfig.from_dict(FAST_CONFIG),
                           mentor="driver")
    for td, ep in zip(rollouts, dataset.iterate_episodes(), strict=True):
        assert np.array_equal(ep.actions, td["next", "behavior_action"].numpy())
        assert np.array_equal(ep.infos["agent_action"][1:], td["action"].numpy())
        for key in ("intervention", "intervention_start", "intervention_cost", "mentor_action", "physics_action",
                    "mentor_selected"):
            assert np.array_equal(ep.infos[key][1:], _flat(td["next", key])), key
        assert np.array_equal(ep.infos["velocity"][0], _flat(td["velocity"])[0])  # a rollout has the reset's info
    for td, (back, meta) in zip(rollouts, read_minari("pe-rlhf/rollout-v0"), strict=True):
        assert torch.equal(back["action"], td["action"]) and torch.equal(back["observation"], td["observation"])
        for key in back["next"].keys():
            assert back["next", key].dtype == td["next", key].dtype, key
            assert torch.equal(back["next", key], td["next", key]), key
        assert set(back["next"].keys()) == set(td["next"].keys())
        assert meta["options"]["scene_seed"] == int(td["next", "scene_seed"][0])


def test_a_dataset_of_another_env_is_refused(minari_root, tmp_path):
    import gymnasium as gym
    from minari.data_collector import EpisodeBuffer

    box = gym.spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
    episode = EpisodeBuffer(observations=np.zeros((3, 3), np.float32), actions=np.zeros((2, 3), np.float32),
                            rewards=np.zeros(2), terminations=np.zeros(2, bool), truncations=np.zeros(2, bool))
    with pytest.warns(UserWarning):  # minari's advice (author, ...)
        minari.create_dataset_from_buffers("other/thing-v0", [episode], observation_space=box, action_space=box)
    with pytest.raises(ValueError, match="only driving datasets"):
        import_minari("other/thing-v0", tmp_path / "d")
    assert not (tmp_path / "d").exists()


def test_cli_export_then_import(recorded, minari_root, tmp_path, capsys):
    assert cli.main(["demo", "export", str(recorded), "--to", "minari", "--out", "pe-rlhf/cli-v0"]) == 0
    assert "exported 3 episodes (100 steps)" in capsys.readouterr().out
    assert cli.main(["demo", "import", "pe-rlhf/cli-v0", "--out", str(tmp_path / "back")]) == 0
    out = capsys.readouterr().out
    assert "imported 3 episodes (100 steps)" in out and "mentor driver" in out
    with pytest.raises(SystemExit) as exit_:
        cli.main(["demo", "export", str(recorded), "--out", "pe-rlhf/cli-v0"])  # exists
    assert exit_.value.code == 2 and "already exists" in capsys.readouterr().err


def test_a_relative_path_is_relative_to_the_current_directory(recorded, tmp_path, monkeypatch):
    """``--out ./exports/driver-v2`` as docs/data-and-logging.md shows: the dataset lands there, once."""
    monkeypatch.delenv("MINARI_DATASETS_PATH", raising=False)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["demo", "export", str(recorded), "--to", "minari", "--out", "./exports/driver-v2"]) == 0
    assert minari.MinariDataset(tmp_path / "exports" / "driver-v2" / "data").total_steps == 100
    assert sorted(p.name for p in (tmp_path / "exports").iterdir()) == ["driver-v2"]  # no staging folder left
    assert export_minari(recorded, "../" + tmp_path.name + "/more/driver-v3")["episodes"] == 3
    assert (tmp_path / "more" / "driver-v3" / "data" / "metadata.json").is_file()


def test_a_failure_mid_way_leaves_nothing_and_the_same_export_can_run_again(recorded, minari_root):
    """The HDF5 file is written, then the metadata cannot be: the staged dataset is removed, not half kept."""
    episodes = directory_episodes(recorded)
    with pytest.raises(TypeError):
        write_minari(episodes, "pe-rlhf/half-v0", env_config=CONFIG, mentor="driver", metadata={"bad": object()})
    assert not (minari_root / "pe-rlhf").exists()
    assert [p.name for p in minari_root.iterdir()] == []  # no staging folder either
    dataset = write_minari(episodes, "pe-rlhf/half-v0", env_config=CONFIG, mentor="driver", metadata={"ok": 1})
    assert dataset.total_steps == 100 and dataset.storage.metadata["pe_rlhf"] == {"ok": 1}
    assert minari.load_dataset("pe-rlhf/half-v0").total_episodes == 3
    with pytest.raises(ValueError, match="already exists"):  # a complete dataset is never overwritten
        write_minari(episodes, "pe-rlhf/half-v0", env_config=CONFIG, mentor="driver")
    assert minari.load_dataset("pe-rlhf/half-v0").total_episodes == 3
