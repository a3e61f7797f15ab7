"""Tests for evaluation: episodes, summaries, policies, the report and the CLI (real env, no mocks)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from rich.console import Console
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from pe_rlhf.apps.cli import main
from pe_rlhf.envs import make_gym_env, scene_seeds
from pe_rlhf.evaluation import (
    POLICY_FACTORIES,
    RandomPolicy,
    TorchRLPolicyAdapter,
    evaluate,
    fit_label,
    make_policy,
    print_summary,
    register_policy,
    run_episode,
    write_json,
)

STAT_KEYS = (
    "episodic_return", "success_rate", "safety_violation", "travel_distance", "travel_velocity",
    "overtake_count", "crash_vehicle_rate", "crash_object_rate", "out_of_road_rate", "timeout_rate",
    "route_completion",
)


@pytest.fixture(scope="module")
def idm_summary() -> dict:
    return evaluate(make_policy("idm-mobil"), scene_seeds("test")[:3], progress=False, name="idm-mobil").to_dict()


class RecordingPolicy:
    """Wraps a policy and keeps the actions it returned."""

    def __init__(self, policy):
        self.policy, self.actions = policy, []

    def reset(self) -> None:
        self.policy.reset()

    def __call__(self, obs, env):
        action = self.policy(obs, env)
        self.actions.append(action.copy())
        return action


def test_run_episode_matches_a_replay_of_its_actions():
    env = make_gym_env(None)
    policy = RecordingPolicy(RandomPolicy(seed=3))
    result = run_episode(env, policy, scene_seed=1000)
    assert result.steps == len(policy.actions) >= 1
    assert result.scene_seed == 1000 and not result.success

    env.reset(options={"scene_seed": 1000})
    rewards, costs, done = [], [], False
    for action in policy.actions:
        assert not done
        _, reward, terminated, truncated, info = env.step(action)
        rewards.append(reward)
        costs.append(info["cost"])
        done = terminated or truncated
    assert done  # the episode ended exactly where run_episode stopped
    assert result.episodic_return == pytest.approx(sum(rewards))
    assert result.safety_violation == sum(costs)
    assert result.travel_distance == pytest.approx(info["travel_distance"])


def test_evaluate_is_deterministic_and_complete(idm_summary):
    again = evaluate(make_policy("idm-mobil"), scene_seeds("test")[:3], progress=False, name="idm-mobil").to_dict()
    assert json.dumps(again) == json.dumps(idm_summary)
    for key in STAT_KEYS:
        assert set(idm_summary[key]) == {"mean", "std"}, key
        assert all(isinstance(v, float) for v in idm_summary[key].values())
    assert 0.0 <= idm_summary["success_rate"]["mean"] <= 1.0
    assert idm_summary["episodes"] == 3 and idm_summary["seeds"] == [1000, 1001, 1002]
    assert idm_summary["policy"] == "idm-mobil"
    assert idm_summary["env_config"]["traffic_density"] == 0.5
    detail = idm_summary["episodes_detail"]
    failed = sum(not e["success"] for e in detail)
    assert sum(idm_summary["failure_breakdown"].values()) == failed
    assert idm_summary["success_rate"]["mean"] == pytest.approx(1 - failed / 3)
    assert idm_summary["episodic_return"]["std"] == pytest.approx(np.std([e["episodic_return"] for e in detail]))


def test_random_policy_never_succeeds():
    summary = evaluate(make_policy("random", seed=0), scene_seeds("test")[:5], progress=False).to_dict()
    assert summary["success_rate"] == {"mean": 0.0, "std": 0.0}
    assert sum(summary["failure_breakdown"].values()) == 5


def test_policy_registry():
    with pytest.raises(ValueError, match="allowed: .*idm-mobil"):
        make_policy("nobody")
    register_policy("test-random", lambda seed: RandomPolicy(seed + 1))
    try:
        assert make_policy("test-random", 1).seed == 2
        with pytest.raises(ValueError, match="already registered"):
            register_policy("test-random", RandomPolicy)
    finally:
        POLICY_FACTORIES.pop("test-random")
    a, b = make_policy("random", 7), make_policy("random", 7)
    assert np.array_equal(a(None, None), b(None, None))


def test_torchrl_adapter_drives_an_episode():
    torch.manual_seed(0)
    actor = TensorDictSequential(
        TensorDictModule(nn.Linear(250, 2), in_keys=["observation"], out_keys=["action"]),
        TensorDictModule(torch.tanh, in_keys=["action"], out_keys=["action"]),
    )
    policy = TorchRLPolicyAdapter(actor)
    env = make_gym_env(None)
    obs, _ = env.reset(options={"scene_seed": 1001})
    action = policy(obs, env)
    assert action.shape == (2,) and action.dtype == np.float32 and np.all(np.abs(action) <= 1)
    result = run_episode(env, RecordingPolicy(policy), scene_seed=1001)
    assert result.steps >= 1


def test_report_renders_and_json_is_atomic(idm_summary, tmp_path):
    console = Console(record=True, width=140)
    print_summary([("idm-mobil", idm_summary), ("again", idm_summary)], console=console)
    text = console.export_text()
    assert "Stage I" in text and "Stage III" in text and "success" in text and "±" in text
    assert "again" in text
    narrow = Console(record=True, width=80)
    print_summary(idm_summary, console=narrow)
    text = narrow.export_text()
    assert "overtakes" in text and "…" not in text  # stacked "mean / ± std" cells, headers intact
    assert max(len(line) for line in text.splitlines()) <= 80
    path = write_json(tmp_path / "nested" / "dir" / "s.json", idm_summary)
    assert json.loads(path.read_text()) == json.loads(json.dumps(idm_summary))
    assert [p.name for p in path.parent.iterdir()] == ["s.json"]  # no temp file left behind


def test_labels_fit_on_one_line():
    """A run folder's label (``agent:<path>``) keeps the run's name and never wraps over rows."""
    assert fit_label("agent:/work/runs/sweeps/claims/pe-rlhf__professional__s0") == "agent:pe-rlhf__professional__s0"
    assert fit_label("agent:runs/hc/checkpoints/ckpt_000030000") == "agent:hc/checkpoints/ckpt_000030000"
    assert fit_label("agent:/work/runs/sweeps/claims/pe-rlhf__professional__s0", 28) == "pe-rlhf__professional__s0"
    assert fit_label("agent:/r/" + "x" * 50, 20) == "…" + "x" * 19
    assert fit_label("idm-mobil") == "idm-mobil" and fit_label("C:/runs/a") == "a"


@pytest.mark.parametrize("width", [80, 120])
def test_report_keeps_a_long_run_label_on_one_row(idm_summary, width):
    label = "agent:/work/runs/sweeps/claims_forecast/pe-rlhf__professional__s0"
    console = Console(record=True, width=width)
    print_summary([(label, idm_summary), ("idm-mobil", idm_summary)], console=console)
    lines = console.export_text().splitlines()
    assert max(len(line) for line in lines) <= width
    shown = fit_label(label, 10 if width == 80 else 28)
    assert sum(shown in line for line in lines) == 2  # one row in each table, nowhere folded
    if width == 120:
        assert shown == "pe-rlhf__professional__s0" and "overtakes" in "".join(lines)


def test_cli_evaluate_writes_json(tmp_path, capsys):
    out = tmp_path / "o.json"
    assert main(["evaluate", "--policy", "random", "--seeds", "1000,1001", "--json", str(out), "--no-progress"]) == 0
    data = json.loads(out.read_text())
    assert data["episodes"] == 2 and data["seeds"] == [1000, 1001] and data["policy"] == "random"
    assert "Stage I" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--policy", "no-such-policy"], "no-such-policy"),
        (["--config-override", "nonsense=1"], "nonsense"),
        (["--config-override", "lanes=7"], "lanes"),
        (["--config-override", "traffic_density=fast"], "traffic_density"),
        (["--split", "test", "--episodes", "51"], "--episodes 51"),
        (["--seeds", "9-3"], "bad seeds"),
    ],
)
def test_cli_rejects_bad_arguments(extra, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--no-progress", *extra])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_cli_config_override_reaches_the_env(tmp_path):
    out = tmp_path / "o.json"
    main(["evaluate", "--policy", "random", "--seeds", "1000", "--json", str(out), "--no-progress",
          "--config-override", "traffic_density=0.8", "--config-override", "lanes=2"])
    config = json.loads(out.read_text())["env_config"]
    assert config["traffic_density"] == 0.8 and config["lanes"] == 2


def test_torchrl_adapter_uses_the_deterministic_action_of_a_probabilistic_actor():
    from tensordict.nn import NormalParamExtractor
    from torchrl.modules import ProbabilisticActor, TanhNormal

    torch.manual_seed(0)
    net = TensorDictModule(nn.Sequential(nn.Linear(250, 4), NormalParamExtractor()),
                           in_keys=["observation"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(net, in_keys=["loc", "scale"], distribution_class=TanhNormal)
    policy = TorchRLPolicyAdapter(actor)
    obs = np.random.default_rng(0).uniform(-1, 1, 250).astype(np.float32)
    first, second = policy(obs, None), policy(obs, None)
    assert first.shape == (2,) and np.array_equal(first, second)
