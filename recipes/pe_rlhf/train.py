"""PE-RLHF training recipe (HACO with ``selector.enabled=false physics.enabled=false``).

    python recipes/pe_rlhf/train.py [profile=cpu|smoke|quick|paper] [group.key=value ...] [--out DIR]
    python recipes/pe_rlhf/train.py --resume DIR      # continue a killed run from its last checkpoint
    python recipes/pe_rlhf/train.py profile=smoke --cfg job   # print the composed config, run nothing

TorchRL's layout: ``config.yaml`` beside this script (a Hydra config over the structured config
:class:`~pe_rlhf.algorithms.proxy_q.config_schema.RecipeConfig`), and everything reusable in
``pe_rlhf.algorithms.proxy_q``; the ``@hydra.main`` function hands the composed config to
:func:`pe_rlhf.algorithms.proxy_q.recipe.hydra_task`. A bad value prints one line ``error: ...`` and exits 2;
``PE_RLHF_DEBUG=1`` shows the traceback.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pe_rlhf.algorithms.proxy_q import recipe

CONFIG = Path(__file__).with_name("config.yaml")


@hydra.main(config_path=".", config_name="config", version_base=None)
def train(cfg: DictConfig) -> dict:
    return recipe.hydra_task(cfg)


def main(argv: list[str] | None = None) -> dict:
    """The command line as a function (tests, ``pe-rlhf sweep``): ``main(["profile=smoke", "--out", "runs/x"])``."""
    return recipe.main(argv, config_path=CONFIG, description=__doc__.splitlines()[0])


if __name__ == "__main__":
    recipe.run_script(train, CONFIG)
