"""Issue 45, case 10: a test's kill time is seeded, so a failure can be replayed (``PE_RLHF_KILL_SEED``)."""

from __future__ import annotations

from _runs import KILL_SEED_VAR, kill_rng


def test_the_kill_time_replays_from_its_seed(monkeypatch, capsys):
    monkeypatch.setenv(KILL_SEED_VAR, "1234")
    first = [kill_rng("a").uniform(0.0, 1.0) for _ in range(3)]
    second = [kill_rng("a").uniform(0.0, 1.0) for _ in range(3)]
    assert first == second
    assert "kill seed 1234 (replay: PE_RLHF_KILL_SEED=1234" in capsys.readouterr().out
    monkeypatch.delenv(KILL_SEED_VAR)
    kill_rng("b")
    seed = int(capsys.readouterr().out.split("kill seed ")[1].split()[0])
    monkeypatch.setenv(KILL_SEED_VAR, str(seed))
    assert kill_rng("b").random() == kill_rng("b").random()
