"""QEnsembleTDLoss: the TD target and both regressions on hand-built critics, the target action's noise and clip,
key renaming, SoftUpdate on its target copy, and fit_q_ensemble as a loop around it (the same numbers as the
hand-written loop it replaced)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from pe_rlhf.modules import QEnsemble, add_next_actions
from pe_rlhf.objectives import QEnsembleTDLoss, fit_q_ensemble

pytestmark = [pytest.mark.usefixtures("one_thread_module"),  # tiny nets: one thread
              # most tests evaluate the loss without a SoftUpdate, which torchrl rightly warns about
              pytest.mark.filterwarnings("ignore:No target network updater:UserWarning")]

OBS, ACT = 3, 2


def _linear_in_action(const: list[float], coef: list[float]) -> QEnsemble:
    """Members ``Q_k(s, a) = const_k + coef_k * a_0`` exactly, for ``a_0`` in [-1, 1] (one ReLU unit holding
    ``a_0 + 1 >= 0``)."""
    k = len(const)
    q = QEnsemble(OBS, ACT, k, (2,))
    c, w = torch.tensor(const), torch.tensor(coef)
    p = q.ensemble.params_td
    with torch.no_grad():
        for leaf in p.values(True, True):
            leaf.zero_()
        p["module", "mlp", "0", "weight"][:, 0, OBS] = 1.0  # unit 0 reads a_0
        p["module", "mlp", "0", "bias"][:, 0] = 1.0
        p["module", "mlp", "2", "weight"][:, 0, 0] = w
        p["module", "mlp", "2", "bias"][:, 0] = c - w
    return q


def _batch(n: int = 4, *, next_a0: list[float] | None = None) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    next_action = torch.zeros(n, ACT)
    if next_a0 is not None:
        next_action[:, 0] = torch.tensor(next_a0)
    return TensorDict({"observation": torch.randn(n, OBS, generator=g),
                       "action": torch.rand(n, ACT, generator=g) * 2 - 1,
                       "next": {"observation": torch.randn(n, OBS, generator=g),
                                "action": next_action,
                                "reward": torch.tensor([[1.0], [-2.0], [0.5], [3.0]])[:n],
                                "terminated": torch.tensor([[False], [True], [False], [True]])[:n]}}, [n])


# --- the target and the two regressions ------------------------------------------------------------

@pytest.mark.parametrize("regression", ["mean", "member"])
def test_constant_critics_give_the_closed_form_target_and_loss(regression):
    """Q_1 = 1, Q_2 = 3 everywhere: y = r + 0.9 * (1 - terminated) * 2; terminal rows y = r."""
    q = _linear_in_action([1.0, 3.0], [0.0, 0.0])
    loss = QEnsembleTDLoss(q, gamma=0.9, target_noise=0.0, regression=regression)
    out = loss(_batch())
    y = torch.tensor([1.0 + 1.8, -2.0, 0.5 + 1.8, 3.0])
    assert out["td_target"].item() == pytest.approx(y.mean().item(), abs=1e-6)
    assert out["q_value"].item() == pytest.approx(2.0, abs=1e-6)
    assert out["q_spread"].item() == pytest.approx(1.0, abs=1e-6)  # population std of {1, 3}
    if regression == "mean":
        expected = (y - 2.0).pow(2).mean()  # only the members' mean is regressed
    else:
        expected = ((1.0 - y).pow(2).mean() + (3.0 - y).pow(2).mean()) / 2  # each member
    assert out["loss_qvalue"].item() == pytest.approx(expected.item(), rel=1e-6)
    assert set(out.keys()) == set(loss.out_keys)
    assert out["loss_qvalue"].requires_grad and not out["td_target"].requires_grad


def test_target_action_is_noised_then_clipped_and_the_noise_comes_from_the_global_rng():
    """Q_k = a_0 (both members): y = r + gamma * (1 - terminated) * clip(a0' + sigma * eps, -1, 1)."""
    q = _linear_in_action([0.0, 0.0], [1.0, 1.0])
    loss = QEnsembleTDLoss(q, gamma=0.5, target_noise=0.5)
    td = _batch(next_a0=[0.95, 0.0, -0.2, 0.5])
    torch.manual_seed(0)
    y = loss.td_target(td)
    torch.manual_seed(0)
    eps = torch.randn(4, ACT)
    noisy = torch.tensor([0.95, 0.0, -0.2, 0.5]) + 0.5 * eps[:, 0]
    assert noisy[0] > 1.0  # this seed's draw pushes row 0 past the bound: the clip is exercised
    expected = td["next", "reward"].squeeze(-1) + 0.5 * (~td["next", "terminated"].squeeze(-1)).float() \
        * noisy.clamp(-1.0, 1.0)
    torch.testing.assert_close(y, expected, rtol=0, atol=1e-6)
    assert y[0].item() == pytest.approx(1.0 + 0.5 * 1.0, abs=1e-6)

    quiet = QEnsembleTDLoss(q, gamma=0.5, target_noise=0.0)
    state = torch.get_rng_state()
    y0 = quiet.td_target(td)
    assert torch.equal(torch.get_rng_state(), state)  # no noise, no draw
    torch.testing.assert_close(y0, td["next", "reward"].squeeze(-1)
                               + 0.5 * torch.tensor([0.95, 0.0, -0.2, 0.0]), rtol=0, atol=1e-6)


def test_gradient_reaches_the_ensemble_only_and_the_input_is_not_written():
    torch.manual_seed(0)
    q = QEnsemble(OBS, ACT, 3, (8,))
    loss = QEnsembleTDLoss(q)
    td = _batch()
    before = td.clone()
    loss(td)["loss_qvalue"].backward()
    assert all(p.grad is not None for p in q.parameters() if p.dim() and p.shape[0] == 3)
    assert all(p.grad is None and not p.requires_grad for p in loss.target_qvalue_network.parameters())
    assert (td == before).all() and set(td.keys(True, True)) == set(before.keys(True, True))


def test_any_batch_shape_is_flattened():
    q = _linear_in_action([1.0, 3.0], [0.5, -0.5])
    loss = QEnsembleTDLoss(q, target_noise=0.0)
    td = _batch()
    flat, stacked = loss(td), loss(td.reshape(2, 2))
    assert all(torch.equal(flat[k], stacked[k]) for k in loss.out_keys)


# --- keys ------------------------------------------------------------------------------------------

def test_set_keys_renames_every_key_read():
    q = _linear_in_action([1.0, 3.0], [0.5, -0.5])
    loss = QEnsembleTDLoss(q, gamma=0.9, target_noise=0.2)
    td = _batch(next_a0=[0.1, 0.2, 0.3, 0.4])
    torch.manual_seed(4)
    reference = loss(td)

    renamed = TensorDict({"obs": td["observation"], ("agent", "act"): td["action"],
                          "next": {"obs": td["next", "observation"], "rew": td["next", "reward"],
                                   "ended": td["next", "terminated"]},
                          ("data_policy", "next_act"): td["next", "action"]}, [4])
    loss.set_keys(observation="obs", action=("agent", "act"), next_action=("data_policy", "next_act"),
                  reward="rew", terminated="ended")
    assert set(loss.in_keys) == {"obs", ("agent", "act"), ("next", "obs"), ("data_policy", "next_act"),
                                 ("next", "rew"), ("next", "ended")}
    torch.manual_seed(4)
    out = loss(renamed)
    assert all(torch.equal(out[k], reference[k]) for k in loss.out_keys)
    with pytest.raises(KeyError):
        loss(td)  # the default names are no longer read
    loss.set_keys(observation=None, action=None, next_action=None, reward=None, terminated=None)
    assert set(loss.in_keys) == {"observation", "action", ("next", "observation"), ("next", "action"),
                                 ("next", "reward"), ("next", "terminated")}


def test_constructor_validates():
    q = QEnsemble(OBS, ACT, 2, (4,))
    with pytest.raises(TypeError, match="QEnsemble"):
        QEnsembleTDLoss(torch.nn.Linear(2, 1))
    for kwargs, word in (({"gamma": 1.5}, "gamma"), ({"target_noise": -0.1}, "target_noise"),
                         ({"regression": "median"}, "regression")):
        with pytest.raises(ValueError, match=word):
            QEnsembleTDLoss(q, **kwargs)


# --- the target copy -------------------------------------------------------------------------------

def test_soft_update_moves_the_target_copy_by_tau():
    torch.manual_seed(0)
    q = QEnsemble(OBS, ACT, 2, (8,))
    loss = QEnsembleTDLoss(q)
    target = loss.target_qvalue_network_params
    assert (target == q.ensemble.params_td).all() and target is not q.ensemble.params_td
    updater = SoftUpdate(loss, tau=0.25)
    old_target = target.clone()
    with torch.no_grad():
        for p in q.ensemble.params_td.values(True, True):
            p.add_(1.0)
    updater.step()
    expected = old_target.apply(lambda t: t + 0.25)
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(target.values(True, True), expected.values(True, True)))
    with torch.no_grad():  # the target network reads the moved parameters
        td = _batch()
        assert not torch.equal(loss.target_qvalue_network.values(td["observation"], td["action"]),
                               q.values(td["observation"], td["action"]))


# --- the fit around it -----------------------------------------------------------------------------

def _chain_data(n: int = 256) -> TensorDict:
    """Two states: A=[1,0,0] loops to itself (r=1), B=[0,1,0] ends (r=1, terminal); actions random."""
    g = torch.Generator().manual_seed(0)
    obs = torch.zeros(n, OBS)
    obs[: n // 2, 0] = 1
    obs[n // 2:, 1] = 1
    term = torch.zeros(n, 1, dtype=torch.bool)
    term[n // 2:] = True
    td = TensorDict({"observation": obs, "action": torch.rand(n, ACT, generator=g) * 2 - 1,
                     "next": {"observation": obs, "reward": torch.ones(n, 1), "terminated": term,
                              "done": term.clone()}}, [n])
    return add_next_actions(td)


@pytest.mark.parametrize("regression", ["mean", "member"])
def test_fit_lowers_the_loss_on_the_whole_data(regression):
    data = _chain_data()
    torch.manual_seed(0)
    q = QEnsemble(OBS, ACT, 3, (32,))

    def full_loss() -> float:
        with torch.no_grad():
            return QEnsembleTDLoss(q, gamma=0.5, target_noise=0.0, regression=regression)(data)["loss_qvalue"].item()

    before = full_loss()
    info = fit_q_ensemble(q, data, steps=300, gamma=0.5, lr=3e-3, tau=0.05, target_noise=0.0, batch_size=64,
                          loss=regression)
    assert full_loss() < 0.05 * before
    assert info["final_loss"] < 0.05 * info["first_loss"]
    with torch.no_grad():
        v = q.values(torch.eye(OBS)[:2], torch.zeros(2, ACT)).mean(0)
    assert v.tolist() == pytest.approx([2.0, 1.0], abs=0.15)  # 1 / (1 - 0.5) and the terminal 1


def _fit_as_before(ensemble: QEnsemble, data: TensorDict, *, steps: int, batch_size: int, gamma: float, lr: float,
                   target_noise: float, tau: float, loss: str, seed: int) -> torch.Tensor:
    """The hand-written loop ``fit_q_ensemble`` was before the LossModule (TensorDict data), kept as the
    reference the loss must reproduce bit for bit."""
    keys = ["observation", "action", ("next", "observation"), ("next", "reward"), ("next", "terminated"),
            ("next", "action")]
    flat = data.select(*keys).reshape(-1)
    history = torch.zeros(steps)
    optim = torch.optim.Adam(ensemble.ensemble.params_td.parameters(), lr=lr)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        target = QEnsemble(**ensemble.config)
        target.load_state_dict(ensemble.state_dict())
        target.requires_grad_(False)
        online_p = [p for _, p in sorted(ensemble.ensemble.params_td.items(True, True), key=lambda kv: str(kv[0]))]
        target_p = [p for _, p in sorted(target.ensemble.params_td.items(True, True), key=lambda kv: str(kv[0]))]
        for step in range(steps):
            batch = flat[torch.randint(flat.shape[0], (batch_size,))]
            obs, act = batch["observation"], batch["action"]
            n = obs.shape[0]
            reward = batch["next", "reward"].reshape(n).to(obs.dtype)
            term = batch["next", "terminated"].reshape(n).to(obs.dtype)
            with torch.no_grad():
                next_act = batch["next", "action"]
                if target_noise > 0:
                    next_act = next_act + target_noise * torch.randn_like(next_act)
                next_act = next_act.clamp(-1.0, 1.0)
                y = reward + gamma * (1.0 - term) * target.values(batch["next", "observation"], next_act).mean(0)
            q = ensemble.values(obs, act)
            value = (y - q.mean(0)).pow(2).mean() if loss == "mean" else (q - y).pow(2).mean()
            optim.zero_grad(set_to_none=True)
            value.backward()
            optim.step()
            with torch.no_grad():
                torch._foreach_lerp_(target_p, online_p, tau)
            history[step] = value.detach()
    return history


@pytest.mark.parametrize("regression", ["mean", "member"])
def test_fit_is_bit_identical_to_the_loop_it_replaced(regression):
    data = _chain_data()
    data["next", "reward"] = torch.randn(data.shape[0], 1, generator=torch.Generator().manual_seed(2))
    kwargs = dict(steps=40, batch_size=32, gamma=0.9, lr=1e-3, target_noise=0.2, tau=0.05, loss=regression, seed=7)
    fitted = []
    for fit in (_fit_as_before, fit_q_ensemble):
        torch.manual_seed(3)
        q = QEnsemble(OBS, ACT, 3, (16, 16))
        out = fit(q, data, **kwargs)
        history = out if isinstance(out, torch.Tensor) else out["loss_history"]
        fitted.append((history, q.state_dict()))
    (h_old, s_old), (h_new, s_new) = fitted
    assert torch.equal(h_old, h_new)
    assert s_old.keys() == s_new.keys() and all(torch.equal(s_old[k], s_new[k]) for k in s_old)
