"""The imitation, offline and human-in-the-loop baseline recipes: BC, CQL, GAIL, HG-DAgger, IWR.

A 200-step professional demonstration set is recorded once (smoke world: horizon 50, one block); each
recipe trains its smoke profile on it and must write every output with finite numbers; a recipe without
``data.path`` records its own; every smoke run moves every actor parameter and a parameter of every optimiser;
HG-DAgger's gate keeps exactly the takeover steps with the mentor's action; IWR's weights balance takeover and
other samples; BC moves the actor toward its labels (and honours weights); GAIL's discriminator separates the
mentor's steps; bad config values fail naming the field.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from _learning import assert_trained, watched_main

from pe_rlhf.algorithms.baselines import METHODS, load_baseline_actor, load_baseline_config, main
from pe_rlhf.algorithms.baselines.demos import ensure_demonstrations, load_transitions
from pe_rlhf.algorithms.baselines.imitation import (
    DiscriminatorLoss,
    WeightedBCLoss,
    executed_steps,
    fit_epochs,
    gail_reward,
    hg_dagger_select,
    iwr_weights,
    make_discriminator,
)
from pe_rlhf.evaluation import TorchRLPolicyAdapter
from pe_rlhf.evaluation.evaluate import MEAN_STD_METRICS
from pe_rlhf.mentors.recording import dataset_info
from pe_rlhf.modules import make_actor
from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.metrics_logger import read_metrics_csv
from pe_rlhf.runtime.update import update
from pe_rlhf.runtime.world import obs_dim

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.filterwarnings("ignore::FutureWarning"), pytest.mark.filterwarnings("ignore::UserWarning")]

IL_METHODS = ("bc", "cql", "gail", "hg_dagger", "iwr")
OUTPUTS = ("config.yaml", "metrics.csv", "final_eval.json", "learning_curves.png", "actor.safetensors")
SIX_METRICS = ("episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
               "overtake_count")
DEMO_STEPS = 200  # the smoke profile's data.steps


@pytest.fixture(scope="session")
def demos_dir(tmp_path_factory) -> Path:
    """200 steps of the professional on the smoke world's train scenes (recorded once per session)."""
    directory = tmp_path_factory.mktemp("demos") / "professional"
    cfg = load_baseline_config("bc", overrides=["profile=smoke"])
    ensure_demonstrations(cfg, directory, progress=False)
    return directory


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory, demos_dir):
    """``smoke_runs(method)``: the run folder of ``train.py profile=smoke data.path=<demos>`` and its parameters
    before and after training (``watched_main``), once per module."""
    done: dict[str, tuple[Path, dict]] = {}

    def run(method: str) -> tuple[Path, dict]:
        if method not in done:
            out = tmp_path_factory.mktemp(method)
            done[method] = out, watched_main(method, ["profile=smoke", f"data.path={demos_dir}", "--out", str(out)])
        return done[method]

    return run


@pytest.fixture(scope="module")
def smoke_run(smoke_runs):
    """``smoke_run(method)``: the run folder of ``smoke_runs(method)``."""
    return lambda method: smoke_runs(method)[0]


def check_outputs(out: Path, method: str) -> tuple[list[dict[str, float]], dict]:
    """Every output exists with finite numbers; returns the metrics rows and final_eval.json."""
    for name in OUTPUTS:
        assert (out / name).is_file(), f"{method}: {name} missing"
    assert (out / "learning_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    cfg = load_baseline_config(method, out / "config.yaml", apply_profile=False)
    assert cfg.method == method and cfg.profile == "smoke"

    columns, rows = read_metrics_csv(out / "metrics.csv")
    assert rows and all(math.isfinite(v) for row in rows for v in row.values())
    needed = {"env_steps", "wall_time", "train/safety_violations_total", "train/mentor_data_total",
              "train/mentor_data_share"}
    if METHODS[method].family == "hil":
        needed |= {"train/takeover_rate", "train/takeover_data_usage", "train/takeover_count",
                   "train/episode_return", "train/success_rate_total"}
    if method == "gail":
        needed |= {"train/gail_reward", "train/d_policy", "train/d_expert", "loss/discriminator", "loss/objective"}
    assert needed <= set(columns), f"{method}: {needed - set(columns)} not logged"
    assert any(c.startswith("loss/") for c in columns)
    violations = [r["train/safety_violations_total"] for r in rows if "train/safety_violations_total" in r]
    assert violations == sorted(violations)  # cumulative

    final = OmegaConf.to_container(OmegaConf.load(out / "final_eval.json"))
    assert final["method"] == METHODS[method].name and final["episodes"] == 1
    assert all(math.isfinite(final[k]["mean"]) for k in SIX_METRICS + MEAN_STD_METRICS)
    assert final["training"]["demo_steps"] == DEMO_STEPS

    actor = load_baseline_actor(out)  # actor.pt, weights_only, into make_actor
    action = TorchRLPolicyAdapter(actor)(np.zeros(obs_dim(cfg), dtype=np.float32), None)
    assert action.shape == (2,) and bool((np.abs(action) <= 1).all())
    return rows, final


# --------------------------------------------------------------------------- smoke runs


@pytest.mark.parametrize("method", IL_METHODS)
def test_smoke_run_writes_every_output(smoke_run, method):
    rows, final = check_outputs(smoke_run(method), method)
    if METHODS[method].family == "offline":
        assert [r["step"] for r in rows] == [r["updates"] for r in rows]
        assert rows[-1]["updates"] == final["training"]["updates"] == load_baseline_config(
            method, overrides=["profile=smoke"]).optim.updates
        assert final["training"]["env_steps"] == 0 and rows[-1]["train/mentor_data_total"] == DEMO_STEPS
    else:
        assert rows[-1]["env_steps"] == final["training"]["env_steps"] == 300
    if METHODS[method].family == "hil":
        t = final["training"]
        assert rows[0]["env_steps"] == 0 and "loss/bc" in rows[0]  # the BC warm-up on the demonstrations
        assert t["mentor_data_total"] == DEMO_STEPS + t["takeover_steps_total"]
        assert t["takeover_data_usage"] == pytest.approx(t["takeover_steps_total"] / 300)
        expected = DEMO_STEPS + (t["takeover_steps_total"] if method == "hg_dagger" else 300)
        assert t["dataset_size"] == expected  # HG-DAgger keeps the takeovers, IWR every step
        assert t["mentor_data_share"] == pytest.approx(t["mentor_data_total"] / expected)


@pytest.mark.parametrize("method", IL_METHODS)
def test_every_il_baseline_trains_its_actor_and_every_optimiser(smoke_runs, method):
    """Issue 45, case 10: in the smoke run every actor parameter moved, and a parameter of every optimiser."""
    assert_trained(method, smoke_runs(method)[1])


def test_cql_trains_the_actor_on_its_bc_term_first(smoke_run):
    """Smoke: ``loss.bc_steps`` 20 of 60 updates, a row every 20: the BC actor term, then CQL's."""
    _, rows = read_metrics_csv(smoke_run("cql") / "metrics.csv")
    assert [r["step"] for r in rows] == [20, 40, 60]
    assert "loss/actor_bc" in rows[0] and "loss/actor" not in rows[0]
    assert all("loss/actor" in r and "loss/actor_bc" not in r for r in rows[1:])
    assert all("loss/cql" in r and "loss/qvalue" in r for r in rows)


def test_recipe_records_its_demonstrations_when_data_path_is_missing(tmp_path):
    out = tmp_path / "bc"
    main("bc", ["profile=smoke", "data.steps=60", "optim.updates=20", "optim.updates_per_iteration=10",
                "--out", str(out)])
    info = dataset_info(out / "demos")
    assert info["mentor"] == "professional" and info["split"] == "train" and info["steps"] >= 60
    assert OmegaConf.load(out / "final_eval.json").training.demo_steps == 60
    cfg = load_baseline_config("bc", overrides=["profile=smoke", "data.steps=120"])
    ensure_demonstrations(cfg, out / "demos", progress=False)  # a larger data.steps extends the same dataset
    assert dataset_info(out / "demos")["steps"] >= 120
    assert torch.equal(load_transitions(cfg, out / "demos")["observation"][:60],
                       load_transitions(load_baseline_config("bc", overrides=["profile=smoke", "data.steps=60"]),
                                        out / "demos")["observation"])


def test_offline_resume_continues_from_the_last_checkpoint(tmp_path, demos_dir):
    out = tmp_path / "run"
    main("bc", ["profile=smoke", f"data.path={demos_dir}", "optim.updates=50", "--out", str(out)])
    main("bc", ["--resume", str(out), "optim.updates=100"])
    _, rows = read_metrics_csv(out / "metrics.csv")
    assert [r["step"] for r in rows] == [25, 50, 75, 100]
    assert (out / "checkpoints" / "latest").read_text().strip() == "ckpt_000000100"
    assert OmegaConf.load(out / "final_eval.json").training.updates == 100


def test_hil_resume_keeps_the_aggregated_dataset_and_the_takeover_counts(tmp_path, demos_dir):
    """IWR to 200 env steps, continued to 300: the dataset (demonstrations + every step) and the counters are
    restored from the checkpoint, the BC warm-up is not repeated."""
    out = tmp_path / "run"
    main("iwr", ["profile=smoke", f"data.path={demos_dir}", "collector.total_frames=200", "--out", str(out)])
    first = OmegaConf.to_container(OmegaConf.load(out / "final_eval.json"))["training"]
    main("iwr", ["--resume", str(out), "collector.total_frames=300"])
    _, rows = read_metrics_csv(out / "metrics.csv")
    assert [r["step"] for r in rows] == [0, 100, 200, 300]
    t = OmegaConf.to_container(OmegaConf.load(out / "final_eval.json"))["training"]
    assert t["dataset_size"] == DEMO_STEPS + 300 and t["demo_steps"] == DEMO_STEPS
    assert t["takeover_steps_total"] >= first["takeover_steps_total"]
    assert t["takeover_steps_total"] == pytest.approx(rows[-1]["train/takeover_steps_total"])


# --------------------------------------------------------------------------- gate and weights


def collected_batch(flags: list[bool], batch_shape=None) -> tuple[TensorDict, torch.Tensor, torch.Tensor]:
    """A batch as the collector writes it under InterventionTransform (no selector): root ``action`` the
    agent's proposal, ``("next", "behavior_action")`` the mentor's action on takeover steps, the agent's
    elsewhere; the root ``intervention`` is the previous step's flag (the transform's reset/step carry-over)."""
    t = len(flags)
    takeover = torch.tensor(flags).unsqueeze(-1)
    obs = torch.arange(t, dtype=torch.float32).unsqueeze(-1).repeat(1, 3)
    agent, mentor = torch.full((t, 2), -0.5), torch.stack([torch.arange(t) / t, -torch.arange(t) / t], -1).float()
    td = TensorDict({"observation": obs, "action": agent,
                     "intervention": torch.cat([torch.zeros(1, 1, dtype=torch.bool), takeover[:-1]]),
                     "next": {"intervention": takeover, "behavior_action": torch.where(takeover, mentor, agent),
                              "mentor_action": mentor}}, [t])
    return (td.reshape(*batch_shape) if batch_shape else td), obs, mentor


@pytest.mark.parametrize("batch_shape", [None, (2, 4)])
def test_hg_dagger_select_keeps_exactly_the_takeover_steps_with_the_mentors_action(batch_shape):
    flags = [False, True, True, False, False, True, False, True]
    batch, obs, mentor = collected_batch(flags, batch_shape)
    picked = hg_dagger_select(batch)
    idx = torch.tensor([i for i, f in enumerate(flags) if f])
    assert picked.batch_size == torch.Size([len(idx)])
    assert torch.equal(picked["observation"], obs[idx])
    assert torch.equal(picked["action"], mentor[idx])  # the mentor's action is the label
    assert bool(picked["intervention"].all())
    assert len(hg_dagger_select(collected_batch([False] * 4)[0])) == 0


def test_executed_steps_keep_every_step_with_the_executed_action_and_its_flag():
    flags = [False, True, True, False]
    batch, obs, _ = collected_batch(flags)
    rows = executed_steps(batch)
    assert torch.equal(rows["observation"], obs)
    assert torch.equal(rows["intervention"].squeeze(-1), torch.tensor(flags))
    assert torch.equal(rows["action"], batch["next", "behavior_action"])


@pytest.mark.parametrize("flags", [[True, False, False, False, False], [True, True, False], [False, True] * 6])
def test_iwr_weights_give_takeover_and_other_samples_equal_total_weight(flags):
    rows = TensorDict({"intervention": torch.tensor(flags).unsqueeze(-1)}, [len(flags)])
    w = iwr_weights(rows)
    mask = torch.tensor(flags)
    assert w.shape == (len(flags),) and bool((w > 0).all())
    assert float(w[mask].sum()) == pytest.approx(float(w[~mask].sum()))
    assert float(w.sum()) == pytest.approx(len(flags))  # mean weight 1
    assert torch.equal(iwr_weights(collected_batch(flags)[0]), w)  # a collected batch: next's flags


@pytest.mark.parametrize("flags", [[True] * 4, [False] * 4])
def test_iwr_weights_are_uniform_with_all_or_no_takeovers(flags):
    assert torch.equal(iwr_weights(TensorDict({"intervention": torch.tensor(flags).unsqueeze(-1)}, [4])),
                       torch.ones(4))


# --------------------------------------------------------------------------- BC and GAIL pieces


def deterministic_action(actor, obs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return actor(TensorDict({"observation": obs}, [obs.shape[0]]))["action"]


@pytest.mark.parametrize("function", ["nll", "mse"])
def test_bc_reduces_its_loss_and_moves_the_action_toward_the_labels(function):
    torch.manual_seed(0)
    obs = torch.randn(128, 6)
    labels = torch.tanh(obs[:, :2] * 0.8)
    data = TensorDict({"observation": obs, "action": labels}, [128])
    actor = make_actor(6, hidden=(32, 32))
    loss = WeightedBCLoss(actor, function)
    opt = {"actor": torch.optim.Adam(actor.parameters(), lr=3e-3)}
    before_loss = float(loss(data)["loss_bc"])
    before_err = float(((deterministic_action(actor, obs) - labels) ** 2).mean())
    fit_epochs(loss, opt, data, epochs=60, batch_size=32, max_grad_norm=None)
    assert float(loss(data)["loss_bc"]) < before_loss - 0.5 * abs(before_loss)
    assert float(((deterministic_action(actor, obs) - labels) ** 2).mean()) < 0.2 * before_err


def test_weighted_bc_fits_the_weighted_mean_of_conflicting_labels():
    """Same state, labels +0.5 (weight 3) and -0.5 (weight 1): MSE-BC's minimiser is their weighted mean."""
    torch.manual_seed(0)
    obs = torch.ones(8, 4)
    labels = torch.tensor([[0.5, 0.5]] * 4 + [[-0.5, -0.5]] * 4)
    weights = torch.tensor([1.5] * 4 + [0.5] * 4)
    actor = make_actor(4, hidden=(16,))
    loss = WeightedBCLoss(actor, "mse")
    fit_epochs(loss, {"actor": torch.optim.Adam(actor.parameters(), lr=1e-2)},
               TensorDict({"observation": obs, "action": labels}, [8]), epochs=300, batch_size=8,
               max_grad_norm=None, weights=weights)
    assert deterministic_action(actor, obs[:1]) == pytest.approx(torch.tensor([[0.25, 0.25]]), abs=0.03)


def test_gail_discriminator_learns_the_mentors_steps_and_rewards_them():
    torch.manual_seed(0)
    disc = make_discriminator(3, hidden=[32])
    loss = DiscriminatorLoss(disc)
    opt = {"discriminator": torch.optim.Adam(disc.parameters(), lr=1e-2)}

    class NoTargets:
        def step(self):
            pass

    def steps(shift):
        return torch.randn(64, 3) + shift, torch.tanh(torch.randn(64, 2) * 0.3 + shift)

    for _ in range(150):
        (eo, ea), (po, pa) = steps(1.0), steps(-1.0)
        td = TensorDict({"observation": eo, "action": ea, "collector_observation": po, "collector_action": pa}, [64])
        out = update(loss, opt, NoTargets(), td, None)
    assert out["loss_discriminator"] < 0.3
    (eo, ea), (po, pa) = steps(1.0), steps(-1.0)
    expert = gail_reward(disc, TensorDict({"observation": eo, "action": ea}, [64]))
    policy = gail_reward(disc, TensorDict({"observation": po, "action": pa}, [64]))
    assert expert.shape == (64, 1) and bool((policy >= 0).all())
    assert float(expert.mean()) > float(policy.mean()) + 1.0


# --------------------------------------------------------------------------- configs


@pytest.mark.parametrize("method, override, field", [
    ("bc", "optim.batch_size=1000", "optim.batch_size"),  # > data.steps (smoke: 200)
    ("bc", "data.steps=0", "data.steps"),
    ("bc", "data.mentor=human", "data.mentor"),
    ("bc", "loss.function=l1", "loss.function"),
    ("cql", "loss.temperature=0", "loss.temperature"),
    ("cql", "optim.updates_per_iteration=1000", "optim.updates_per_iteration"),  # > optim.updates (smoke: 60)
    ("gail", "discriminator.lr=-1", "discriminator.lr"),
    ("gail", "optim.minibatch_size=1000", "optim.minibatch_size"),  # > collector.frames_per_batch
    ("hg_dagger", "mentor.name=human", "mentor.name"),
    ("hg_dagger", "optim.updates=5", "optim.updates"),  # an offline field on an online method
    ("iwr", "mentor.kwargs.no_such_field=1", "mentor.kwargs.no_such_field"),
    ("iwr", "collector.frames_per_batch=1000", "collector.frames_per_batch"),  # > total_frames (smoke: 300)
    ("iwr", "eval.every_updates=5", "eval.every_updates"),
])
def test_bad_config_value_fails_naming_the_field(method, override, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")) as err:
        load_baseline_config(method, overrides=["profile=smoke", override])
    assert err.value.field == field


def test_bad_config_value_stops_the_command_line_before_training(tmp_path):
    with pytest.raises(ConfigError, match=r"optim\.epochs"):
        main("iwr", ["profile=smoke", "optim.epochs=0", "--out", str(tmp_path / "run")])
    assert not (tmp_path / "run").exists()
