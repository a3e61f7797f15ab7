"""NaN/inf in a loss term, a gradient or a parameter stops updates with a message naming it; the
trainer saves a checkpoint of everything collected first. Each case runs with the recipe's default loss
(``loss.objective=proxy_value``, ProxyValueLoss) and with the paper's (PERLHFLoss): the guard is the same
:func:`~pe_rlhf.runtime.update.update` for both."""

from __future__ import annotations

import copy

import pytest
import torch
from _runs import train

from pe_rlhf.objectives import PERLHFLoss, ProxyValueLoss
from pe_rlhf.runtime.checkpoint import find_checkpoint, load_checkpoint
from pe_rlhf.runtime.update import nonfinite_parameters, update
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.filterwarnings("ignore::UserWarning")]

LOSSES = {"proxy_value": ProxyValueLoss, "paper": PERLHFLoss}  # loss.objective -> its loss (the default first)
# the term poisoned in each loss: the proxy-value critics', the paper's intervention critic
POISONED_TERM = {"proxy_value": "loss_qvalue", "paper": "loss_intervention_qvalue"}
# the optimizer whose step the parameter test follows: the paper's alpha (SAC's), else the critics'
STEPPED = {"proxy_value": "qvalue", "paper": "alpha"}


@pytest.fixture(params=list(LOSSES))
def learner(request):
    cfg = load_config(overrides=["profile=smoke", f"loss.objective={request.param}"])
    actor = builders.build_actor(cfg)
    loss, soft_update = builders.build_loss(cfg, actor)
    optimizers = builders.build_optimizers(cfg, loss)
    from pe_rlhf.objectives.perlhf import make_transitions

    g = torch.Generator().manual_seed(0)
    n, obs = 16, obs_dim(cfg)
    takeover = torch.rand(n, 1, generator=g) < 0.5
    sample = make_transitions(torch.randn(n, obs, generator=g), torch.randn(n, obs, generator=g),
                              torch.rand(n, 2, generator=g) * 2 - 1, torch.rand(n, 2, generator=g) * 2 - 1,
                              takeover, takeover.clone(), torch.zeros(n, 1, dtype=torch.bool))
    assert isinstance(loss, LOSSES[request.param])
    return loss, optimizers, soft_update, sample


# ProxyValueLoss's call count (TD3's actor delay) counts every forward, the one that computed a bad term included:
# a count, not a parameter or a target; everything else in the loss's state must be untouched
COUNTS = ("calls",)


def loss_name(loss) -> str:
    return next(name for name, cls in LOSSES.items() if isinstance(loss, cls))


def params(loss) -> dict:
    return copy.deepcopy({k: v.detach() for k, v in loss.state_dict().items() if k not in COUNTS})


def unchanged(before: dict, loss) -> bool:
    now = {k: v for k, v in loss.state_dict().items() if k not in COUNTS}
    return set(before) == set(now) and all(torch.equal(before[k], v) for k, v in now.items())


def test_non_finite_loss_term_is_named_and_nothing_changes(learner, monkeypatch):
    loss, optimizers, soft_update, sample = learner
    cls = type(loss)
    real, term = cls.forward, POISONED_TERM[loss_name(loss)]

    def forward(self, td):
        out = real(self, td)
        out[term] = out[term] * float("inf")
        return out

    monkeypatch.setattr(cls, "forward", forward)
    before = params(loss)
    with pytest.raises(FloatingPointError, match=f"{term} is inf"):
        update(loss, optimizers, soft_update, sample, max_grad_norm=10.0)
    assert unchanged(before, loss)


@pytest.mark.parametrize("max_grad_norm", [10.0, None])
def test_non_finite_gradient_names_the_optimizer_and_no_step_is_taken(learner, max_grad_norm):
    loss, optimizers, soft_update, sample = learner
    if isinstance(loss, ProxyValueLoss):  # the actor learns on every policy_delay-th update (TD3): make it this one
        loss.calls.fill_(loss.policy_delay - 1)
    weight = next(iter(loss.actor_network_params.values(True, True)))
    weight.register_hook(lambda g: torch.full_like(g, float("nan")))
    before = params(loss)
    with pytest.raises(FloatingPointError, match="gradient of optimizer 'actor' has norm nan"):
        update(loss, optimizers, soft_update, sample, max_grad_norm=max_grad_norm)
    assert unchanged(before, loss)  # no optimizer stepped, targets untouched


def test_non_finite_parameter_after_a_step_is_named(learner, monkeypatch):
    loss, optimizers, soft_update, sample = learner
    opt = optimizers[STEPPED[loss_name(loss)]]
    real_step = opt.step
    param = opt.param_groups[0]["params"][0]  # the paper's log_alpha; the first critic weight
    [name] = [n for n, p in loss.named_parameters() if p is param]
    assert name == "log_alpha" or not isinstance(loss, PERLHFLoss)

    def step(*a, **k):
        real_step(*a, **k)
        with torch.no_grad():
            param.fill_(float("inf"))

    monkeypatch.setattr(opt, "step", step)
    with pytest.raises(FloatingPointError, match=rf"parameters \[{name!r}\] became non-finite"):
        update(loss, optimizers, soft_update, sample, max_grad_norm=10.0)
    assert nonfinite_parameters(loss) == [name]


@pytest.mark.parametrize("objective", list(LOSSES))
def test_trainer_saves_a_checkpoint_then_stops_naming_the_term(tmp_path, monkeypatch, objective):
    """A NaN loss on the 5th update (the third batch of 25 frames, after 2 updates a batch from
    frame 25): the run stops with the term named, after a checkpoint holding all 75 frames."""
    cls = LOSSES[objective]
    real = cls.forward
    calls = []

    def forward(self, td):
        out = real(self, td)
        calls.append(1)
        if len(calls) == 5:
            out["loss_qvalue"] = out["loss_qvalue"] * float("nan")
        return out

    monkeypatch.setattr(cls, "forward", forward)
    out = tmp_path / "run"
    with pytest.raises(FloatingPointError, match=r"loss_qvalue is nan .*Saved checkpoint .*ckpt_000000075 \(frame 75"):
        train(out, "collector.total_frames=200", f"loss.objective={objective}")
    assert len(calls) == 5  # the run built this loss
    ckpt = find_checkpoint(out / "checkpoints")
    assert ckpt.name == "ckpt_000000075"
    cfg = load_config(out / "config.yaml", apply_profile=False)
    replay = builders.build_replay_buffer(cfg, balanced=True)  # as the run built it (takeover rows apart)
    state = load_checkpoint(ckpt, modules={}, optimizers={}, replay_buffers={"replay": replay}, strict=False)
    assert len(replay) == 75 and state["counters"]["frames"] == 75 and state["counters"]["updates"] == 4
