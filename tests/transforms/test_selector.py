"""HybridActionSelector: the selection rule, isolated with an estimator whose values are exact."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from pe_rlhf.modules.q_ensemble import QEnsemble
from pe_rlhf.transforms.selector import HybridActionSelector

OBS, ACT = 3, 2
SLOPES = (-3.0, -1.0, 1.0, 3.0)  # mean 0, population std sqrt(5)


class ExactQ(QEnsemble):
    """Test double of the estimator: ``Q_k(s, a) = a[0] + SLOPES[k] * a[1]`` exactly.

    The members' mean is ``a[0]`` (so the advantage is ``mentor[0] - physics[0]``) and their
    population std is ``sqrt(5) * |a[1]|``. It isolates the selection rule from any training.
    """

    def __init__(self):
        super().__init__(OBS, ACT, num_members=len(SLOPES), hidden=(4,))
        self.calls = []

    def values(self, observation, action):
        self.calls.append((observation.shape, torch.is_grad_enabled()))
        slopes = torch.tensor(SLOPES).reshape(-1, *([1] * (action.dim() - 1)))
        return action[..., 0] + slopes * action[..., 1]


def _acts(x0, x1=0.0, batch=()):
    return torch.tensor([x0, x1], dtype=torch.float32).expand(*batch, ACT).clone()


def test_default_epsilon_is_papers():
    assert HybridActionSelector(ExactQ()).epsilon_select == 0.5


@pytest.mark.parametrize("eps", [0.5, 0.1, 0.0, -0.25])
def test_boundary_equal_chooses_mentor_just_below_chooses_physics(eps):
    sel = HybridActionSelector(ExactQ(), epsilon_select=eps)
    obs = torch.zeros(1, OBS)
    at = torch.tensor(eps, dtype=torch.float32)  # advantage exactly eps (as float32)
    below = torch.nextafter(at, torch.tensor(-1.0))
    phy = _acts(0.0, batch=(1,))
    hybrid, chosen = sel.select(obs, torch.stack([at, torch.tensor(0.0)])[None], phy)
    assert chosen.item() is True and hybrid[0, 0].item() == at.item()
    hybrid, chosen = sel.select(obs, torch.stack([below, torch.tensor(0.0)])[None], phy)
    assert chosen.item() is False and torch.equal(hybrid, phy)


def test_batched_matches_row_by_row_and_runs_the_ensemble_once():
    q = ExactQ()
    sel = HybridActionSelector(q, epsilon_select=0.5)
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(64, OBS, generator=g)
    mentor = torch.rand(64, ACT, generator=g) * 2 - 1
    phy = torch.rand(64, ACT, generator=g) * 2 - 1
    mentor[:8, 0] = phy[:8, 0] + 0.5  # some rows near the boundary
    hybrid, chosen = sel.select(obs, mentor, phy)
    assert len(q.calls) == 1 and q.calls[0][0] == (128, OBS)  # both actions in one call
    assert hybrid.shape == (64, ACT) and chosen.shape == (64, 1) and chosen.dtype == torch.bool
    assert 5 < chosen.sum() < 59  # genuinely mixed decisions
    for i in range(64):
        h_i, c_i = sel.select(obs[i], mentor[i], phy[i])
        assert c_i.item() == chosen[i].item()
        assert torch.equal(h_i, hybrid[i])
        assert torch.equal(hybrid[i], mentor[i] if c_i.item() else phy[i])


def test_unbatched_inputs():
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.5)
    hybrid, chosen = sel.select(torch.zeros(OBS), _acts(1.0), _acts(0.0))
    assert hybrid.shape == (ACT,) and chosen.shape == (1,) and chosen.item() is True
    assert torch.equal(hybrid, _acts(1.0))
    hybrid, chosen = sel.select(torch.zeros(OBS), _acts(0.2), _acts(0.0))
    assert chosen.item() is False and torch.equal(hybrid, _acts(0.0))


def test_extra_batch_dims():
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.5)
    mentor = _acts(1.0, batch=(4, 3))
    mentor[1, 2, 0] = 0.0
    hybrid, chosen = sel.select(torch.zeros(4, 3, OBS), mentor, _acts(0.0, batch=(4, 3)))
    assert hybrid.shape == (4, 3, ACT) and chosen.shape == (4, 3, 1)
    assert chosen.sum().item() == 11 and not chosen[1, 2].item()


def test_variance_escape():
    obs = torch.zeros(2, OBS)
    mentor = _acts(-0.5, batch=(2,))  # advantage -1: physics wins on the mean
    phy = torch.tensor([[0.5, 1.0], [0.5, 0.0]])  # row 0: members disagree (std sqrt 5); row 1: they agree
    _, chosen = HybridActionSelector(ExactQ()).select(obs, mentor, phy)
    assert chosen[:, 0].tolist() == [False, False]
    _, chosen = HybridActionSelector(ExactQ(), variance_threshold=1.0).select(obs, mentor, phy)
    assert chosen[:, 0].tolist() == [True, False]
    _, chosen = HybridActionSelector(ExactQ(), variance_threshold=2.5).select(obs, mentor, phy)
    assert chosen[:, 0].tolist() == [False, False]  # sqrt(5) = 2.236 is not above 2.5


@pytest.mark.parametrize("kwargs", [{"epsilon_select": float("nan")}, {"epsilon_select": float("inf")},
                                    {"epsilon_select": -float("inf")}, {"variance_threshold": -0.1}])
def test_invalid_parameters_raise(kwargs):
    with pytest.raises(ValueError):
        HybridActionSelector(ExactQ(), **kwargs)


def test_selection_runs_without_grad():
    q = ExactQ()
    sel = HybridActionSelector(q)
    sel.select(torch.zeros(2, OBS), _acts(1.0, batch=(2,)), _acts(0.0, batch=(2,)))
    assert q.calls[-1][1] is False
    real = QEnsemble(OBS, ACT, 3, (8,))  # a real (trainable) ensemble: no graph is built
    hybrid, _ = HybridActionSelector(real, epsilon_select=-1e9).select(
        torch.zeros(2, OBS), _acts(1.0, batch=(2,)).requires_grad_(), _acts(0.0, batch=(2,)))
    assert not hybrid.requires_grad


def test_frozen_ensemble_works():
    real = QEnsemble(OBS, ACT, 3, (8,))
    real.requires_grad_(False)
    hybrid, chosen = HybridActionSelector(real).select(torch.zeros(5, OBS), _acts(1.0, batch=(5,)),
                                                       _acts(0.0, batch=(5,)))
    assert hybrid.shape == (5, ACT) and chosen.shape == (5, 1)


def test_tensordict_module_form():
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.5)
    mentor = _acts(1.0, batch=(6,))
    mentor[::2, 0] = 0.0
    td = TensorDict({"observation": torch.zeros(6, OBS), "mentor_action": mentor,
                     "physics_action": _acts(0.0, batch=(6,))}, [6])
    out = sel(td)
    assert out is td
    assert td["hybrid_action"].shape == (6, ACT) and td["hybrid_action"].dtype == torch.float32
    assert td["mentor_selected"].shape == (6, 1) and td["mentor_selected"].dtype == torch.bool
    assert td["mentor_selected"][:, 0].tolist() == [False, True] * 3
    assert sel.in_keys == ["observation", "mentor_action", "physics_action"]
    assert sel.out_keys == ["hybrid_action", "mentor_selected"]
    # unbatched tensordict
    td1 = sel(TensorDict({"observation": torch.zeros(OBS), "mentor_action": _acts(1.0),
                          "physics_action": _acts(0.0)}, []))
    assert td1["hybrid_action"].shape == (ACT,) and td1["mentor_selected"].shape == (1,)


@pytest.mark.parametrize("previous, advantage, chosen", [
    (None, 0.4, False), (None, 0.5, True),     # a takeover's first step: the plain rule
    (True, -0.4, True), (True, -0.6, False),   # on the mentor: stays until eps - margin (-0.5)
    (False, 1.4, False), (False, 1.5, True),   # on physics: moves back only at eps + margin (1.5)
])
def test_switch_margin_makes_a_takeovers_choice_sticky(previous, advantage, chosen):
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.5, switch_margin=1.0)
    _, got = sel.select(torch.zeros(OBS), _acts(advantage), _acts(0.0), previous)
    assert got.item() is chosen


def test_without_switch_margin_the_previous_choice_is_ignored():
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.5)
    for previous in (None, True, False):
        assert sel.select(torch.zeros(OBS), _acts(0.4), _acts(0.0), previous)[1].item() is False


def test_an_infinite_switch_margin_commits_to_the_first_choice():
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.5, switch_margin=float("inf"))
    assert sel.select(torch.zeros(OBS), _acts(-100.0), _acts(0.0), True)[1].item() is True
    assert sel.select(torch.zeros(OBS), _acts(100.0), _acts(0.0), False)[1].item() is False


def test_switch_margin_batched_previous():
    sel = HybridActionSelector(ExactQ(), epsilon_select=0.0, switch_margin=1.0)
    mentor = torch.tensor([[-0.5, 0.0], [-0.5, 0.0], [0.5, 0.0], [0.5, 0.0]])
    previous = torch.tensor([[True], [False], [True], [False]])
    _, chosen = sel.select(torch.zeros(4, OBS), mentor, torch.zeros(4, ACT), previous)
    assert chosen.squeeze(-1).tolist() == [True, False, True, False]


@pytest.mark.parametrize("margin", [-1.0, float("nan"), "1", True])
def test_invalid_switch_margin_raises(margin):
    with pytest.raises(ValueError, match="switch_margin"):
        HybridActionSelector(ExactQ(), switch_margin=margin)


def _patient(patience=3, imminent=None):
    return HybridActionSelector(ExactQ(), epsilon_select=0.0, veto_patience=patience, imminent_failure=imminent)


def _step(sel, mentor_value, previous, physics_value=0.0):
    _, chosen = sel.select(torch.zeros(OBS), _acts(mentor_value), _acts(physics_value), previous)
    return bool(chosen.item())


def test_a_patient_veto_replaces_the_mentor_only_after_consecutive_vetoes():
    sel = _patient(3)
    # mentor worse at every step: mentor, mentor, then physics from the third veto on
    assert [_step(sel, -1.0, p) for p in (None, True, True, False, False)] == [True, True, False, False, False]
    # a step where the mentor is not vetoed resets the count
    assert [_step(sel, v, p) for v, p in ((-1.0, None), (-1.0, True), (1.0, True), (-1.0, True), (-1.0, True))] \
        == [True, True, True, True, True]
    # a new takeover (previous None) starts counting again
    assert [_step(sel, -1.0, p) for p in (None, True)] == [True, True]


def test_an_imminent_failure_is_vetoed_at_once():
    sel = _patient(5, imminent=0.3)  # ExactQ's value of the mentor is its action's first entry
    assert _step(sel, 0.2, None, physics_value=0.9) is False  # fails within 0.3: at once
    assert _step(sel, 0.5, None, physics_value=0.9) is True  # vetoed, but not imminent: patience
    assert _step(sel, 0.2, None, physics_value=0.1) is True  # imminent but not worse than physics: no veto


def test_patience_one_is_every_step_alone():
    sel, alone = _patient(1), HybridActionSelector(ExactQ(), epsilon_select=0.0)
    for value, previous in ((-1.0, None), (-1.0, True), (1.0, False)):
        assert _step(sel, value, previous) == _step(alone, value, previous)


@pytest.mark.parametrize("kwargs", [{"veto_patience": 0}, {"veto_patience": 1.5}, {"veto_patience": True},
                                    {"imminent_failure": float("nan")}, {"imminent_failure": "soon"}])
def test_invalid_patience_raises(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        HybridActionSelector(ExactQ(), **kwargs)


def test_select_counted_is_select_with_the_count_passed_in_and_out():
    """The stateless form makes the stateful one's choices when handed back the count it returned (zeros, or
    None, at a takeover's start), and leaves the selector's own count alone."""
    sel, stateless = _patient(3), _patient(3)
    streak = None
    for value, previous in ((-1.0, None), (-1.0, True), (-1.0, True), (1.0, False), (-1.0, True), (-1.0, None)):
        if previous is None:
            streak = None
        _, expected = sel.select(torch.zeros(OBS), _acts(value), _acts(0.0), previous)
        _, chosen, streak = stateless.select_counted(torch.zeros(OBS), _acts(value), _acts(0.0), previous, streak)
        assert bool(chosen.item()) == bool(expected.item()) and streak.dtype == torch.long
    assert stateless.streak_state() is None


def test_the_veto_count_survives_a_checkpoint_as_json():
    """``streak_state`` -> JSON -> ``load_streak_state`` in a fresh selector: the third veto replaces the mentor,
    as in the selector that counted the first two; None loads the fresh state (a new takeover's count)."""
    import json

    sel = _patient(3)
    assert [_step(sel, -1.0, p) for p in (None, True)] == [True, True]
    saved = json.loads(json.dumps(sel.streak_state()))
    assert saved == [2]
    restored, fresh = _patient(3), _patient(3)
    restored.load_streak_state(saved)
    fresh.load_streak_state(None)
    assert _step(restored, -1.0, True) is False and _step(sel, -1.0, True) is False
    assert _step(fresh, -1.0, True) is True  # counting from 0: the first veto


class TableForecast(torch.nn.Module):
    """A forecast-like value source from tables: ``values`` reads the first action entry as its one-step value,
    ``repeated_values`` as ``repeated[entry]``, ``recovery_value`` a fixed number (seconds)."""

    needs_env = False

    def __init__(self, repeated: dict[float, float], recovery: float = 0.0):
        super().__init__()
        self.repeated, self.recovery = repeated, recovery

    def values(self, obs, acts):
        return acts[..., 0].reshape(1, -1).float()

    def repeated_values(self, obs, acts):
        return torch.tensor([[self.repeated[round(float(a), 3)] for a in acts[..., 0].reshape(-1)]])

    horizon = 3.0

    def recovery_value(self, env=None):
        return torch.tensor([[self.recovery]])

    def recovery_action(self, env=None):
        return torch.tensor([-9.0, -1.0])  # marked: a steering no policy proposes

    def progress(self, obs, acts):  # the second action entry as metres of progress
        return acts[..., 1].reshape(1, -1).float()


def test_a_latched_veto_holds_until_the_repeated_action_is_safe():
    """One-step values: mentor 2.9 vs physics 3.0 passes eps -0.5, 2.0 does not. Repeated: 2.9 -> 1.0 (unsafe
    when repeated), 2.8 -> 3.0 (safe). After a veto, 2.9 stays vetoed while latched; 2.8 releases the latch."""
    sel = HybridActionSelector(TableForecast({2.9: 1.0, 2.8: 3.0, 2.0: 0.5}), -0.5, persistence="latch")
    obs, phy = torch.zeros(1), torch.tensor([3.0, 0.0])
    steps = [(2.9, True), (2.0, False), (2.9, False), (2.9, False), (2.8, True), (2.9, True)]
    previous = None
    for value, expected in steps:
        _, chosen = sel.select(obs, torch.tensor([value, 0.0]), phy, previous)
        assert bool(chosen) is expected, (value, expected)
        previous = chosen
    always = HybridActionSelector(TableForecast({2.9: 1.0, 2.8: 3.0}), -0.5, persistence="always")
    assert not bool(always.select(obs, torch.tensor([2.9, 0.0]), phy)[1])  # checked even without a veto
    off = HybridActionSelector(TableForecast({2.9: 1.0, 2.0: 0.5}), -0.5)
    assert [bool(off.select(obs, torch.tensor([v, 0.0]), phy, True)[1]) for v in (2.0, 2.9)] == [False, True]


def test_the_recovery_reference_compares_with_braking_at_once_when_physics_looks_worse():
    """Physics' action 0.9 s (its lane change held 1 s), braking now 3.0 s: a mentor at 1.6 s is within 0.5 s of
    physics' action but 1.4 s worse than the recovery, so only the recovery reference vetoes it."""
    obs, mentor, phy = torch.zeros(1), torch.tensor([1.6, 0.0]), torch.tensor([0.9, 0.0])
    plain = HybridActionSelector(TableForecast({}, recovery=3.0), -0.5)
    best = HybridActionSelector(TableForecast({}, recovery=3.0), -0.5, reference="physics_or_recovery")
    assert bool(plain.select(obs, mentor, phy)[1]) and not bool(best.select(obs, mentor, phy)[1])
    hybrid, _, _, _, reference = best.judge(obs, mentor, phy)
    assert reference.item() == pytest.approx(3.0)  # the value it compared with
    assert hybrid.tolist() == [-9.0, -1.0]  # and braking at once is what runs in physics' place
    worse_recovery = HybridActionSelector(TableForecast({}, recovery=0.5), -0.5, reference="physics_or_recovery")
    hybrid, chosen, _, _, reference = worse_recovery.judge(obs, torch.tensor([0.2, 0.0]), phy)
    assert not bool(chosen) and hybrid.tolist() == phy.tolist() and reference.item() == pytest.approx(0.9)


@pytest.mark.parametrize("mentor, physics, chosen", [
    (2.6, 3.0, True),  # physics safe over the horizon: the 0.5 s slack applies
    (1.2, 1.5, False),  # physics itself forecast to fail: no slack, the mentor must be at least as good
    (1.5, 1.5, True),
])
def test_strict_in_danger_removes_the_slack_where_physics_itself_fails(mentor, physics, chosen):
    sel = HybridActionSelector(TableForecast({}), -0.5, strict_in_danger=True)
    assert bool(sel.select(torch.zeros(1), torch.tensor([mentor, 0.0]), torch.tensor([physics, 0.0]))[1]) is chosen
    loose = HybridActionSelector(TableForecast({}), -0.5)
    assert bool(loose.select(torch.zeros(1), torch.tensor([mentor, 0.0]), torch.tensor([physics, 0.0]))[1])


def test_a_safe_action_that_makes_too_little_progress_is_vetoed_with_a_progress_margin():
    """Entries: (seconds to failure, metres of progress held 1 s). Physics safe over the horizon and making
    10 m: a mentor as safe but 1.5 m short is vetoed with a 1 m margin, 0.5 m short is not; without the
    margin safety alone decides. Where physics is itself forecast to fail, progress is not asked."""
    obs, phy = torch.zeros(1), torch.tensor([3.0, 10.0])
    sel = HybridActionSelector(TableForecast({}), -0.5, progress_margin=1.0)
    safety_alone = HybridActionSelector(TableForecast({}), -0.5)
    for mentor, chosen in (([3.0, 8.5], False), ([3.0, 9.5], True), ([2.8, 12.0], True)):
        assert bool(sel.select(obs, torch.tensor(mentor), phy)[1]) is chosen, mentor
        assert bool(safety_alone.select(obs, torch.tensor(mentor), phy)[1])
    in_danger = torch.tensor([2.0, 10.0])
    assert bool(sel.select(obs, torch.tensor([2.5, 0.0]), in_danger)[1])
    latched = HybridActionSelector(TableForecast({3.0: 3.0}), -0.5, persistence="latch", progress_margin=1.0)
    _, chosen, streak, _, _ = latched.judge(obs, torch.tensor([3.0, 8.5]), phy)
    assert not bool(chosen) and streak.tolist() == [1]  # a progress veto is a veto: the latch holds it


class StandingForecast(TableForecast):
    """:class:`TableForecast` with the ego's speed [m/s] set by the test."""

    ego_speed = 0.0

    def speed(self):
        return torch.tensor([self.ego_speed])


def test_a_latch_releases_where_the_car_stands_with_a_latch_release_speed():
    """The professional's deadlock: a full-lock turn around an obstacle at walking pace, safe held 1 s (3.0) but
    leaving the road when repeated for the whole horizon (2.0), once vetoed (1.0) is held for ever. With a release
    speed of 0.5 m/s, a standing car judges the step alone and the mentor drives again; while the car still rolls
    the latch holds."""
    forecast = StandingForecast({3.0: 2.0, 1.0: 2.0})
    obs, phy = torch.zeros(1), torch.tensor([3.0, 0.0])
    held = HybridActionSelector(forecast, -0.5, persistence="latch")
    released = HybridActionSelector(forecast, -0.5, persistence="latch", latch_release_speed=0.5)
    for sel in (held, released):
        _, chosen, streak, _, _ = sel.judge(obs, torch.tensor([1.0, 0.0]), phy)
        assert not bool(chosen) and streak.tolist() == [1]  # the veto
    forecast.ego_speed = 2.0  # braking, still rolling: both hold
    for sel in (held, released):
        _, chosen, streak, _, _ = sel.judge(obs, torch.tensor([3.0, 0.0]), phy, streak=torch.tensor([1]))
        assert not bool(chosen) and streak.tolist() == [1]
    forecast.ego_speed = 0.0  # standing
    assert not bool(held.judge(obs, torch.tensor([3.0, 0.0]), phy, streak=torch.tensor([1]))[1])
    _, chosen, streak, _, _ = released.judge(obs, torch.tensor([3.0, 0.0]), phy, streak=torch.tensor([1]))
    assert bool(chosen) and streak.tolist() == [0]
    _, chosen, streak, _, _ = released.judge(obs, torch.tensor([1.0, 0.0]), phy, streak=torch.tensor([1]))
    assert not bool(chosen) and streak.tolist() == [1]  # standing, the one-step test still vetoes
    for kwargs, match in (({"persistence": "always"}, "needs persistence='latch'"), ({}, "needs persistence"),
                          ({"persistence": "latch", "q": TableForecast({})}, "value source with speed")):
        source = kwargs.pop("q", forecast)
        with pytest.raises(ValueError, match=match):
            HybridActionSelector(source, -0.5, latch_release_speed=0.5, **kwargs)
    with pytest.raises(ValueError, match="latch_release_speed=-1"):
        HybridActionSelector(forecast, -0.5, persistence="latch", latch_release_speed=-1)


@pytest.mark.parametrize("margin", [-1.0, float("nan"), float("inf"), True])
def test_invalid_progress_margin_raises(margin):
    with pytest.raises(ValueError, match="progress_margin"):
        HybridActionSelector(TableForecast({}), -0.5, progress_margin=margin)
    with pytest.raises(ValueError, match="needs a value source"):
        HybridActionSelector(ExactQ(), -0.5, progress_margin=1.0)


@pytest.mark.parametrize("kwargs, match", [
    ({"persistence": "sometimes"}, "persistence='sometimes' is invalid"),
    ({"reference": "mentor"}, "reference='mentor' is invalid"),
    ({"persistence": "latch", "veto_patience": 2}, "use one of them"),
])
def test_invalid_persistence_and_reference_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HybridActionSelector(TableForecast({}), -0.5, **kwargs)


@pytest.mark.parametrize("kwargs", [{"persistence": "latch"}, {"reference": "physics_or_recovery"},
                                    {"strict_in_danger": True}])
def test_persistence_and_reference_need_the_forecast(kwargs):
    with pytest.raises(ValueError, match="needs a value source"):
        HybridActionSelector(ExactQ(), -0.5, **kwargs)
