"""Evaluation: run policies on fixed scenes, summarise the spec's metrics, print and save them.

``scene_plot`` (matplotlib pictures of scenes) is a submodule imported on demand:
``from pe_rlhf.evaluation.scene_plot import draw_scene``.
"""

from pe_rlhf.evaluation.evaluate import EpisodeResult, EvaluationSummary, evaluate, run_episode
from pe_rlhf.evaluation.policies import (
    POLICY_FACTORIES,
    PhysicsPolicyAdapter,
    Policy,
    RandomPolicy,
    TorchRLPolicyAdapter,
    make_policy,
    register_policy,
)
from pe_rlhf.evaluation.report import fit_label, print_summary, summary_tables, write_json

__all__ = [
    "POLICY_FACTORIES",
    "EpisodeResult",
    "EvaluationSummary",
    "PhysicsPolicyAdapter",
    "Policy",
    "RandomPolicy",
    "TorchRLPolicyAdapter",
    "evaluate",
    "fit_label",
    "make_policy",
    "print_summary",
    "register_policy",
    "run_episode",
    "summary_tables",
    "write_json",
]
