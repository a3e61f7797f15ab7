"""IWR baseline recipe (config.yaml beside this file; everything else in pe_rlhf.algorithms.baselines).

    python recipes/iwr/train.py [profile=paper|cpu|smoke] [group.key=value ...] [--out DIR] [--compare idm-mobil]
    python recipes/iwr/train.py --resume DIR      # continue a run from its last checkpoint
    python recipes/iwr/train.py profile=smoke --cfg job   # print the composed config, run nothing

TorchRL's layout: ``config.yaml`` beside this script (a Hydra config over the structured config
:class:`~pe_rlhf.algorithms.baselines.imitation_schema.IWRConfig`); the ``@hydra.main`` function hands the composed
config to :func:`pe_rlhf.algorithms.baselines.cli.hydra_task`. A bad value prints one line ``error: ...`` and exits 2;
``PE_RLHF_DEBUG=1`` shows the traceback.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pe_rlhf.algorithms.baselines import cli

METHOD = "iwr"
CONFIG = Path(__file__).with_name("config.yaml")


@hydra.main(config_path=".", config_name="config", version_base=None)
def train(cfg: DictConfig) -> dict:
    return cli.hydra_task(cfg, METHOD)


def main(argv: list[str] | None = None) -> dict:
    """The command line as a function (tests, ``pe-rlhf sweep``): ``main(["profile=smoke", "--out", "runs/x"])``."""
    return cli.main(METHOD, argv, config_path=CONFIG)


if __name__ == "__main__":
    cli.run_script(train, METHOD, CONFIG)
