"""PVP training recipe: bounded proxy values (ProxyValueLoss), the mentor's takeovers executed as they come.

    python recipes/pvp/train.py [profile=cpu|smoke|paper] [group.key=value ...] [--out DIR]
    python recipes/pvp/train.py --resume DIR      # continue a killed run from its last checkpoint
    python recipes/pvp/train.py profile=smoke --cfg job   # print the composed config, run nothing

The PE-RLHF recipe (``recipes/pe_rlhf``) with ``physics.enabled=false
loss.objective=proxy_value replay_buffer.takeover_share=0.5`` (``config.yaml`` beside this script):
:class:`~pe_rlhf.transforms.InterventionTransform` without physics or selector, and
:class:`~pe_rlhf.objectives.ProxyValueLoss` with a deterministic actor. A bad value prints one line
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
