"""QEnsemble: vectorised members, TD fitting on a toy task with a known Q, save/load."""

from __future__ import annotations

import os

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import EnsembleModule

from pe_rlhf.modules.ensemble_training import add_next_actions
from pe_rlhf.objectives.q_ensemble_fit import fit_q_ensemble
from pe_rlhf.modules.q_ensemble import QEnsemble, load_q_ensemble, save_q_ensemble

OBS, ACT, K = 3, 2, 5


pytestmark = pytest.mark.usefixtures("one_thread_module")  # tiny nets: one thread


# --- the estimator -------------------------------------------------------------------------------

def test_members_differ_at_init_and_params_have_leading_k_dim():
    torch.manual_seed(0)
    q = QEnsemble(OBS, ACT, K, (32, 32))
    assert isinstance(q.ensemble, EnsembleModule)
    params = dict(q.ensemble.params_td.items(True, True))
    assert params and all(p.shape[0] == K for p in params.values())
    out = q.values(torch.zeros(1, OBS), torch.zeros(1, ACT))[:, 0]
    assert out.shape == (K,)
    assert len(set(out.tolist())) == K  # every member gives a different value for the same input
    assert q.config == {"obs_dim": OBS, "action_dim": ACT, "num_members": K, "hidden": (32, 32)}


def test_values_shape_and_one_vectorised_call():
    q = QEnsemble(OBS, ACT, K, (16,))
    calls = []
    q.ensemble.module.module.register_forward_hook(lambda *a: calls.append(1))
    assert q.values(torch.randn(7, OBS), torch.randn(7, ACT)).shape == (K, 7)
    assert len(calls) == 1  # the K members run in one vmap-ed forward, not K forwards
    assert q.values(torch.randn(4, 6, OBS), torch.randn(4, 6, ACT)).shape == (K, 4, 6)
    assert q.values(torch.randn(OBS), torch.randn(ACT)).shape == (K,)
    td = q(TensorDict({"observation": torch.randn(7, OBS), "action": torch.randn(7, ACT)}, [7]))
    assert td["state_action_value"].shape == (K, 7, 1)


def test_requires_grad_false_freezes():
    q = QEnsemble(OBS, ACT, 3, (16,))
    q.requires_grad_(False)
    assert not any(p.requires_grad for p in q.parameters())
    assert not q.values(torch.randn(5, OBS), torch.randn(5, ACT)).requires_grad


# --- add_next_actions ----------------------------------------------------------------------------

def test_add_next_actions_respects_episode_boundaries():
    action = torch.arange(6.0)[:, None].expand(6, ACT).clone()
    done = torch.tensor([0, 0, 1, 0, 1, 0], dtype=torch.bool)[:, None]
    td = TensorDict({"action": action, "next": {"done": done}}, [6])
    add_next_actions(td)
    assert td["next", "action"][:, 0].tolist() == [1.0, 2.0, 2.0, 4.0, 4.0, 5.0]
    # (N, T) rollouts: the time is the last batch dim
    td2 = TensorDict({"action": torch.stack([action, action + 10]),
                      "next": {"done": torch.stack([done, torch.zeros_like(done)])}}, [2, 6])
    add_next_actions(td2)
    assert td2["next", "action"][0, :, 0].tolist() == [1.0, 2.0, 2.0, 4.0, 4.0, 5.0]
    assert td2["next", "action"][1, :, 0].tolist() == [11.0, 12.0, 13.0, 14.0, 15.0, 15.0]


# --- fitting -------------------------------------------------------------------------------------

_W = torch.randn(ACT, OBS, generator=torch.Generator().manual_seed(7))


def _a_star(s):
    return torch.tanh(s @ _W.T)


def _reward(s, a):  # the true Q for gamma = 0
    return -(a - _a_star(s)).pow(2).sum(-1)


def _bandit(n, seed):
    g = torch.Generator().manual_seed(seed)
    s = torch.randn(n, OBS, generator=g)
    a = torch.rand(n, ACT, generator=g) * 2 - 1
    return s, a


def _bandit_data(n=4096, seed=1):
    s, a = _bandit(n, seed)
    return TensorDict({"observation": s, "action": a,
                       "next": {"observation": s, "action": a, "reward": _reward(s, a)[:, None],
                                "terminated": torch.ones(n, 1, dtype=torch.bool)}}, [n])


@pytest.fixture(scope="module")
def fitted():
    """Both loss forms on the contextual bandit r = -||a - a*(s)||^2, gamma = 0 (Q = r)."""
    data = _bandit_data()
    s_test, a_test = _bandit(2000, seed=2)
    out = {}
    for loss in ("mean", "member"):
        torch.manual_seed(0)
        q = QEnsemble(OBS, ACT, K, (64, 64))
        with torch.no_grad():
            mse0 = (q.values(s_test, a_test).mean(0) - _reward(s_test, a_test)).pow(2).mean().item()
        info = fit_q_ensemble(q, data, steps=300, gamma=0.0, lr=3e-3, loss=loss, seed=0)
        out[loss] = (q, info, mse0)
    return out, s_test, a_test


@pytest.mark.parametrize("loss", ["mean", "member"])
def test_fit_learns_known_q(fitted, loss):
    out, s_test, a_test = fitted
    q, info, mse0 = out[loss]
    with torch.no_grad():
        mse = (q.values(s_test, a_test).mean(0) - _reward(s_test, a_test)).pow(2).mean().item()
        g = torch.Generator().manual_seed(3)
        good = (_a_star(s_test) + 0.05 * torch.randn(s_test.shape[0], ACT, generator=g)).clamp(-1, 1)
        bad = torch.rand(s_test.shape[0], ACT, generator=g) * 2 - 1
        far = (bad - _a_star(s_test)).norm(dim=-1) > 0.5
        ranked = (q.values(s_test, good).mean(0) > q.values(s_test, bad).mean(0))[far].float().mean().item()
    print(f"{loss}: held-out MSE {mse0:.3f} -> {mse:.4f} ({mse0 / mse:.0f}x), ranking {ranked:.3f}, "
          f"TD loss {info['first_loss']:.3f} -> {info['final_loss']:.4f}")
    assert ranked > 0.9
    assert mse < mse0 / 50
    assert info["final_loss"] < info["first_loss"] / 20
    assert info["loss_history"].shape == (300,) and info["steps"] == 300 and info["loss"] == loss


def test_member_loss_makes_members_individual_estimates_and_spread_informative(fitted):
    out, s_test, a_test = fitted
    stats = {}
    far_s = torch.randn(2000, OBS, generator=torch.Generator().manual_seed(4)) * 4  # off the data
    with torch.no_grad():
        for loss, (q, _, _) in out.items():
            v = q.values(s_test, a_test)
            stats[loss] = {"member_mse": (v - _reward(s_test, a_test)).pow(2).mean().item(),
                           "spread_in": v.std(0).mean().item(),
                           "spread_out": q.values(far_s, a_test).std(0).mean().item()}
    print(stats)
    m, e = stats["member"], stats["mean"]
    assert m["member_mse"] < e["member_mse"] / 10  # "mean" trains only the average
    assert m["spread_in"] < e["spread_in"] / 5
    assert m["spread_out"] > 2 * m["spread_in"]  # diversity is kept where the data is silent


def test_fit_bootstraps_and_stops_at_termination():
    # obs A=[1,0] loops to itself (r=1, not terminal): Q = 1/(1-gamma) = 2 at gamma 0.5
    # obs B=[0,1] ends (r=1, terminal): Q = 1
    n = 512
    obs = torch.zeros(n, 2)
    obs[: n // 2, 0] = 1
    obs[n // 2:, 1] = 1
    act = torch.zeros(n, 1)
    term = torch.zeros(n, 1, dtype=torch.bool)
    term[n // 2:] = True
    data = TensorDict({"observation": obs, "action": act,
                       "next": {"observation": obs, "action": act, "reward": torch.ones(n, 1),
                                "terminated": term}}, [n])
    torch.manual_seed(0)
    q = QEnsemble(2, 1, 3, (32,))
    fit_q_ensemble(q, data, steps=400, gamma=0.5, lr=3e-3, tau=0.05, target_noise=0.0, batch_size=64)
    with torch.no_grad():
        v = q.values(torch.eye(2), torch.zeros(2, 1)).mean(0)
    assert v[0].item() == pytest.approx(2.0, abs=0.1)
    assert v[1].item() == pytest.approx(1.0, abs=0.1)


def test_fit_from_replay_buffer_seeded_and_restores_frozen_flags():
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    data = _bandit_data(512)
    rb = ReplayBuffer(storage=LazyTensorStorage(512))
    rb.extend(data)
    results = []
    for _ in range(2):
        torch.manual_seed(0)
        q = QEnsemble(OBS, ACT, 3, (16,))
        q.requires_grad_(False)
        rng_before = torch.get_rng_state()
        info = fit_q_ensemble(q, rb, steps=20, batch_size=32, seed=5)
        assert torch.equal(torch.get_rng_state(), rng_before)  # global RNG untouched
        assert not any(p.requires_grad for p in q.parameters())
        results.append((info["loss_history"], q.values(torch.ones(1, OBS), torch.ones(1, ACT))))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    assert torch.isfinite(results[0][0]).all()


def test_fit_validates_inputs():
    q = QEnsemble(OBS, ACT, 2, (8,))
    data = _bandit_data(16)
    with pytest.raises(ValueError, match="loss"):
        fit_q_ensemble(q, data, steps=1, loss="median")
    with pytest.raises(ValueError, match="tau"):
        fit_q_ensemble(q, data, steps=1, tau=0.0)
    with pytest.raises(KeyError, match="add_next_actions"):
        fit_q_ensemble(q, data.exclude(("next", "action")), steps=1)
    info = fit_q_ensemble(q, data, steps=0)
    assert info["steps"] == 0 and info["final_loss"] != info["final_loss"]  # NaN


# --- save / load ---------------------------------------------------------------------------------

def test_save_load_round_trip(tmp_path):
    q = QEnsemble(OBS, ACT, 4, (16, 8))
    path = tmp_path / "q.pt"
    save_q_ensemble(q, path)
    loaded = load_q_ensemble(path, obs_dim=OBS, num_members=4)
    assert loaded.config == q.config
    s, a = torch.randn(10, OBS), torch.randn(10, ACT)
    with torch.no_grad():
        assert torch.equal(q.values(s, a), loaded.values(s, a))
    # the file is plain data: it loads with weights_only=True on its own
    raw = torch.load(path, weights_only=True)
    assert raw["config"] == {"obs_dim": OBS, "action_dim": ACT, "num_members": 4, "hidden": [16, 8]}


def test_load_config_mismatch_names_file(tmp_path):
    path = tmp_path / "q.pt"
    save_q_ensemble(QEnsemble(OBS, ACT, 2, (8,)), path)
    with pytest.raises(ValueError, match="num_members") as err:
        load_q_ensemble(path, num_members=5)
    assert str(path) in str(err.value)
    # a config that does not fit the stored weights
    raw = torch.load(path, weights_only=True)
    raw["config"]["hidden"] = [9]
    torch.save(raw, path)
    with pytest.raises(ValueError) as err:
        load_q_ensemble(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("kind", ["truncated", "garbage", "empty", "foreign"])
def test_load_corrupt_file_raises_value_error_with_path(tmp_path, kind):
    path = tmp_path / f"{kind}.pt"
    if kind == "truncated":
        save_q_ensemble(QEnsemble(OBS, ACT, 2, (8,)), path)
        blob = path.read_bytes()
        path.write_bytes(blob[: len(blob) // 2])
    elif kind == "garbage":
        path.write_bytes(os.urandom(1000))
    elif kind == "empty":
        path.write_bytes(b"")
    else:
        torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(ValueError) as err:
        load_q_ensemble(path)
    assert str(path) in str(err.value)


class _Payload:  # a custom class: unpickling it would run arbitrary code paths
    def __init__(self):
        self.x = 1


def test_load_refuses_pickled_objects(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format": "pe_rlhf.q_ensemble", "version": 1, "config": _Payload(), "state_dict": {}}, path)
    with pytest.raises(ValueError, match="non-weights|not a readable") as err:
        load_q_ensemble(path)
    assert str(path) in str(err.value)


def test_load_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_q_ensemble(tmp_path / "nope.pt")


def test_save_rejects_non_ensemble(tmp_path):
    with pytest.raises(TypeError):
        save_q_ensemble(torch.nn.Linear(2, 2), tmp_path / "x.pt")


def test_ensemble_schedule_frozen_and_refreshed():
    from pe_rlhf.modules.ensemble_training import EnsembleSchedule

    frozen = EnsembleSchedule(warmup_steps=100, warmup_fit_steps=50)
    fits = [(step, frozen.due(step)) for step in range(0, 1000, 10)]
    assert [f for f in fits if f[1]] == [(100, 50)]  # one fit right after warm-up, then frozen

    refreshed = EnsembleSchedule(warmup_steps=100, refresh_every=300, warmup_fit_steps=50, refresh_steps=20)
    fits = [(step, n) for step in range(0, 1000, 10) if (n := refreshed.due(step))]
    assert fits == [(100, 50), (400, 20), (700, 20)]

    resumed = EnsembleSchedule(warmup_steps=100, refresh_every=300)
    resumed.load_state_dict(refreshed.state_dict())
    assert resumed.due(800) == 0 and resumed.due(1000) == 500  # continues, no repeat


def test_ensemble_schedule_rejects_bad_values():
    from pe_rlhf.modules.ensemble_training import EnsembleSchedule

    with pytest.raises(ValueError, match="refresh_every"):
        EnsembleSchedule(warmup_steps=10, refresh_every=-1)


def test_pickles_and_deep_copies_as_config_and_parameters():
    import copy
    import pickle

    q = QEnsemble(OBS, num_members=3, hidden=(16, 16))
    obs, act = torch.randn(4, OBS), torch.rand(4, 2) * 2 - 1
    for clone in (pickle.loads(pickle.dumps(q)), copy.deepcopy(q)):
        assert clone.config == q.config
        torch.testing.assert_close(clone.values(obs, act), q.values(obs, act))
        with torch.no_grad():
            for p in clone.parameters():
                p.add_(1.0)
        assert not torch.allclose(clone.values(obs, act), q.values(obs, act))  # independent of the original
