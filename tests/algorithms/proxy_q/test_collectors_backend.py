"""``collector.backend``: TorchRL's multi-process collectors over per-worker PE-RLHF envs (real simulator).

One ``multisync`` collector with 2 workers is driven once (module fixture: worker start-up costs
~10 s); the tests check what it recorded. ``selector.epsilon_select=-1e9`` makes the selector trust
the mentor whenever the ensemble is finite, so filling the main process's ensemble with NaN in place
must flip every worker-side takeover to physics: that is how the shared weights are seen.
"""

from __future__ import annotations

import csv
import functools
import math
import sys
import types

import pytest
import torch
from _scripts import load_pe_rlhf_recipe
from torchrl.collectors import Collector

from pe_rlhf.runtime.config_rules import ConfigError
from pe_rlhf.runtime.update import update
from pe_rlhf.runtime.world import obs_dim
from pe_rlhf.algorithms.proxy_q import builders
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.steps import batch_metrics, ensemble_transitions

pytestmark = pytest.mark.usefixtures("one_thread_module")

MULTISYNC = ["profile=smoke", "collector.backend=multisync", "collector.num_workers=2"]
TOTAL_FRAMES = 300  # 6 batches of 50 (25 per worker)


@pytest.fixture(scope="module")
def multisync_run(one_thread_module):
    cfg = load_config(overrides=MULTISYNC + ["collector.warmup_steps=2", "selector.value=expert",  # weights to push
                                             "selector.epsilon_select=-1e9"])
    value_source, actor = builders.build_value_source(cfg), builders.build_actor(cfg)
    loss, soft_update = builders.build_loss(cfg, actor)
    optimizers = builders.build_optimizers(cfg, loss)
    collector = builders.build_collector(cfg, None, actor, TOTAL_FRAMES, value_source=value_source)
    run = {"batches": [], "out_key": actor_output(actor)}
    try:
        for i, batch in enumerate(collector):
            run["batches"].append(batch.clone())
            if i == 0:  # real updates, then sync: the next batch must be acted by the updated actor
                before = [p.detach().clone() for p in actor.parameters()]
                # the recipe's ProxyValueLoss (TD3) steps its actor on every policy_delay-th update: hold one
                for _ in range(getattr(loss, "policy_delay", 1)):
                    update(loss, optimizers, soft_update, batch.reshape(-1), max_grad_norm=None)
                run["actor_changed"] = any(not torch.equal(a, p) for a, p in zip(before, actor.parameters()))
                builders.sync_policy(collector)
            elif i == 1:
                with torch.no_grad():
                    run["main_out"] = actor(batch.select("observation").clone()).get(run["out_key"])
                    for p in value_source.parameters():  # in place, after the workers started
                        p.fill_(float("nan"))
    finally:
        builders.shutdown_collector(collector)
    return run


def actor_output(actor) -> str:
    """The key of the actor's deterministic output: the paper's Gaussian mean ``loc`` (its action is sampled), the
    recipe's deterministic actor's ``action`` (``loss.objective=proxy_value``, no exploration noise)."""
    return "loc" if "loc" in actor.out_keys else "action"


def _mentor_chosen(batch) -> tuple[int, int]:
    nxt = batch.get("next")
    takeover = nxt.get("intervention")
    return int((nxt.get("mentor_selected") & takeover).sum()), int(takeover.sum())


def test_multisync_batches_are_per_worker_runs_with_finite_metrics(multisync_run):
    batches = multisync_run["batches"]
    assert all(b.shape == (2, 25) for b in batches)  # (workers, time)
    assert sum(b.numel() for b in batches) == TOTAL_FRAMES
    first = batches[0].get(("next", "scene_seed"))
    assert first[0, 0].item() != first[1, 0].item()  # seeds seed + 0, seed + 1: different scenes
    for batch in batches:
        m = batch_metrics(batch)
        assert m["steps"] == 50 and all(math.isfinite(v) for v in m.values())
        assert batch_metrics(batch.reshape(-1)) == pytest.approx(m)  # flattened for the replay buffer
        flat = ensemble_transitions(batch).reshape(-1)
        assert flat.shape == (50,) and ("next", "action") in flat.keys(True)
        # next action within a worker's run = that worker's next executed action (not the other worker's)
        nxt = ensemble_transitions(batch)
        executed, done = batch.get(("next", "behavior_action")), batch.get(("next", "done")).squeeze(-1)
        keep = ~done[:, :-1]
        assert torch.equal(nxt.get(("next", "action"))[:, :-1][keep], executed[:, 1:][keep])


def test_fitted_ensemble_weights_reach_the_workers(multisync_run):
    batches = multisync_run["batches"]
    # while the ensemble is finite (batches 0 and 1, after each worker's one warm-up step, which the mentor drives
    # unjudged), epsilon -1e9: the mentor is trusted at every takeover. Counted over both together: how many
    # takeovers a batch holds varies from run to run (0 to 26 in batch 1 on one machine)
    early = [_mentor_chosen(batches[0][:, 1:]), _mentor_chosen(batches[1])]
    assert sum(t for _, t in early) > 0 and sum(c for c, _ in early) == sum(t for _, t in early)
    # the main process's ensemble is NaN now: physics is chosen at every later takeover. Over the later batches
    # together: which of them hold a takeover depends on when the workers took the synced actor (a loaded machine
    # gave one without any)
    later = [_mentor_chosen(batch) for batch in batches[2:]]
    assert sum(t for _, t in later) > 0 and sum(c for c, _ in later) == 0


def test_policy_weights_reach_the_workers_after_sync(multisync_run):
    assert multisync_run["actor_changed"]
    worker_out = multisync_run["batches"][1].get(multisync_run["out_key"])
    torch.testing.assert_close(worker_out, multisync_run["main_out"], rtol=1e-5, atol=1e-5)


def test_invalid_backend_combinations_name_the_field():
    with pytest.raises(ConfigError, match="collector.backend='multisync'") as err:
        load_config(overrides=["mentor.name=human", "collector.backend=multisync", "collector.num_workers=2"])
    assert err.value.field == "collector.backend"
    with pytest.raises(ConfigError, match="collector.backend='multiasync'"):
        load_config(overrides=["mentor.name=human", "collector.backend=multiasync", "collector.num_workers=2"])
    with pytest.raises(ConfigError, match="collector.frames_per_batch=50") as err:
        load_config(overrides=MULTISYNC[:2] + ["collector.num_workers=3"])
    assert err.value.field == "collector.frames_per_batch"
    # multiasync yields one worker's full batch at a time: no divisibility needed
    assert load_config(overrides=["profile=smoke", "collector.backend=multiasync", "collector.num_workers=3"])


def test_ray_kwargs_and_ensemble_push_without_ray(monkeypatch):
    cfg = load_config(overrides=MULTISYNC + ["selector.value=warmup"])  # two fresh ensembles differ until pushed
    value_source, actor = builders.build_value_source(cfg), builders.build_actor(cfg)
    factories = [functools.partial(builders.make_worker_env, cfg, worker_index=i, num_workers=2) for i in range(2)]
    kwargs = builders.ray_collector_kwargs(cfg, factories, actor, TOTAL_FRAMES, value_source)
    assert kwargs["num_collectors"] == 2 and kwargs["sync"] and kwargs["collector_class"] is Collector
    assert [f.keywords["worker_index"] for f in kwargs["create_env_fn"]] == [0, 1]
    assert all(f.keywords["value_source"] is value_source for f in kwargs["create_env_fn"])
    # push_value_source_weights: the path it loads into exists on a worker's collector
    worker_ensemble = builders.build_value_source(cfg)
    env = builders.make_worker_env(cfg, 1, 2, value_source=worker_ensemble)
    assert env.transform[-1].warmup_steps == math.ceil(int(cfg.collector.warmup_steps) / 2)
    worker = Collector(env, actor, frames_per_batch=10, total_frames=10)
    remote = types.SimpleNamespace(cascade_execute=types.SimpleNamespace(remote=worker.cascade_execute))
    monkeypatch.setitem(sys.modules, "ray", types.SimpleNamespace(get=lambda futures: futures))
    builders.push_value_source_weights(types.SimpleNamespace(remote_collectors=[remote]), value_source)
    obs, act = torch.randn(3, obs_dim(cfg)), torch.rand(3, 2) * 2 - 1
    torch.testing.assert_close(worker_ensemble.values(obs, act), value_source.values(obs, act))
    worker.shutdown()


def test_smoke_training_with_multisync_writes_finite_metrics(tmp_path):
    # no GIF (a third of a smoke run's CPU): test_training_smoke checks the video
    final = load_pe_rlhf_recipe().main(MULTISYNC + ["eval.video=false", "--out", str(tmp_path)])
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(float(r["step"])) for r in rows] == [50, 100, 150, 200, 250, 300]
    for row in rows:
        for key, value in row.items():
            if value != "":
                assert math.isfinite(float(value)), key
    assert float(rows[0]["train/takeover_rate"]) == 1.0  # warm-up: 50 forced steps per worker
    assert any(r.get("loss/qvalue") for r in rows[1:])
    assert final["training"]["frames"] == 300 and final["training"]["online_frames"] == 200
    assert (tmp_path / "checkpoints").is_dir() and (tmp_path / "actor.safetensors").exists()


# -- collector.backend=ray on a real local Ray instance --------------------------------------------
def test_ray_collector_on_local_ray_acts_with_the_pushed_value_estimator(monkeypatch):
    """Two Ray workers collect PE-RLHF batches; after the learner's ensemble is pushed with NaN weights
    (``push_value_source_weights``, what the trainer does after the warm-up fit), every takeover in the next
    batches executes physics: the workers select with the learner's estimator, not their own copies."""
    ray = pytest.importorskip("ray")
    cfg = load_config(overrides=["profile=smoke", "collector.backend=ray", "collector.num_workers=2",
                                 "collector.frames_per_batch=50", "collector.warmup_steps=2", "selector.value=warmup",
                                 "selector.epsilon_select=-1e9", "mentor.name=adversarial"])
    value_source, actor = builders.build_value_source(cfg), builders.build_actor(cfg)
    monkeypatch.setenv("RAY_worker_niceness", "0")  # Ray's default 15 starves the workers behind other tests
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    batches = []
    try:
        collector = builders.build_collector(cfg, None, actor, 200, value_source=value_source)
        try:
            for i, batch in enumerate(collector):
                batches.append(batch.clone())
                if i == 0:
                    with torch.no_grad():
                        for p in value_source.parameters():
                            p.fill_(float("nan"))
                    builders.push_value_source_weights(collector, value_source)
        finally:
            builders.shutdown_collector(collector)
    finally:
        ray.shutdown()
    assert [b.shape for b in batches] == [torch.Size([2, 25])] * 4  # (workers, time), 200 frames
    first = batches[0].get(("next", "scene_seed"))
    assert first[0, 0].item() != first[1, 0].item()  # each worker its own seed, its own scenes
    before = [_mentor_chosen(b) for b in batches[:1]]
    after = [_mentor_chosen(b) for b in batches[2:]]  # batch 1 may have started before the push landed
    assert sum(t for _, t in after) > 0, "the adversarial mentor took over: takeovers to judge"
    assert before[0][0] > 0  # finite estimator, eps -1e9: the mentor wins
    assert sum(chosen for chosen, _ in after) == 0  # NaN estimator pushed: physics everywhere
