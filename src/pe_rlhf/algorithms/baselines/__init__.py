"""The paper's baselines on the driving env: RL and safe RL (SAC-RS, SAC-Lag, PPO-RS, PPO-Lag, CPO), offline
RL and imitation (BC, CQL, GAIL) and human-in-the-loop imitation (HG-DAgger, IWR).

Each is a recipe (``recipes/<method>/config.yaml`` + a thin ``@hydra.main`` ``train.py``) over these shared parts:
:mod:`~pe_rlhf.algorithms.baselines.config_schema` (each method's structured config: every field's default, type
and rule), :mod:`~pe_rlhf.algorithms.baselines.config_profiles`, :mod:`~pe_rlhf.algorithms.baselines.config`
(Hydra composition, validation), :mod:`~pe_rlhf.algorithms.baselines.algorithms` (the RL learners: TorchRL's
SAC/ClipPPO losses and pe_rlhf's SAC-Lag/PPO-Lag/CPO losses), :mod:`~pe_rlhf.algorithms.baselines.imitation` (BC
loss, HG-DAgger's gate, IWR's weights, GAIL's discriminator) and :mod:`~pe_rlhf.algorithms.baselines.imitation_learners`
(GAIL, HG-DAgger, IWR), :mod:`~pe_rlhf.algorithms.baselines.offline` (BC and CQL on demonstrations),
:mod:`~pe_rlhf.algorithms.baselines.demos` (the demonstrations, recorded when missing),
:mod:`~pe_rlhf.algorithms.baselines.episodes` (training episode bookkeeping), :mod:`~pe_rlhf.algorithms.baselines.loop`
(collect, learn, log, evaluate, checkpoint), :mod:`~pe_rlhf.algorithms.baselines.plots` and
:mod:`~pe_rlhf.algorithms.baselines.cli`.
"""

from pe_rlhf.algorithms.baselines.config import METHODS, Method, default_config, load_baseline_config, profiles
from pe_rlhf.algorithms.baselines.episodes import EpisodeTracker


def load_baseline_actor(run_dir):
    """The trained actor of a baseline run folder (see
    :func:`pe_rlhf.algorithms.baselines.loop.load_baseline_actor`)."""
    from pe_rlhf.algorithms.baselines.loop import load_baseline_actor as load

    return load(run_dir)


def main(method: str, argv: list[str] | None = None) -> dict:
    """Run ``recipes/<method>/train.py``'s command line (see :mod:`pe_rlhf.algorithms.baselines.cli`)."""
    from pe_rlhf.algorithms.baselines.cli import main as cli_main

    return cli_main(method, argv)


__all__ = ["METHODS", "EpisodeTracker", "Method", "default_config", "load_baseline_actor", "load_baseline_config",
           "main", "profiles"]
