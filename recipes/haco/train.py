"""HACO training recipe: PE-RLHF's proxy-Q learner, the mentor's takeovers executed as they come.

    python recipes/haco/train.py [profile=cpu|smoke|paper] [group.key=value ...] [--out DIR]
    python recipes/haco/train.py --resume DIR      # continue a killed run from its last checkpoint
    python recipes/haco/train.py profile=smoke --cfg job   # print the composed config, run nothing

The PE-RLHF recipe (``recipes/pe_rlhf``) with ``physics.enabled=false``
(``config.yaml`` beside this script, a Hydra config over the PE-RLHF recipe's structured config):
:class:`~pe_rlhf.transforms.InterventionTransform` without physics or selector, and the same
:class:`~pe_rlhf.objectives.PERLHFLoss`. The ablation the paper compares PE-RLHF against. A bad value prints one line
``error: ...`` and exits 2; ``PE_RLHF_DEBUG=1`` shows the traceback. The training loop is
``recipes/pe_rlhf/train.py``'s ``train``, run over this folder's config.
"""

from __future__ import annotations

from pathlib import Path

from pe_rlhf.algorithms.proxy_q import recipe

CONFIG = Path(__file__).with_name("config.yaml")
PE_RLHF = recipe.load_recipe_script("pe_rlhf", Path(__file__).parents[1])  # the loop: recipes/pe_rlhf/train.py


def main(argv: list[str] | None = None) -> dict:
    """The command line as a function (tests, ``pe-rlhf sweep``): ``main(["profile=smoke", "--out", "runs/x"])``."""
    return PE_RLHF.main(argv, config=CONFIG)


if __name__ == "__main__":
    PE_RLHF.run_as_script(CONFIG)
