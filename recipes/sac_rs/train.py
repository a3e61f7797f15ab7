"""SAC-RS baseline recipe (config.yaml beside this file; everything else in pe_rlhf.baselines).

    python recipes/sac_rs/train.py [profile=paper|cpu|smoke] [group.key=value ...] [--out DIR] [--compare idm-mobil]
    python recipes/sac_rs/train.py --resume DIR      # continue a run from its last checkpoint

A bad value prints one line ``error: ...`` and exits 2; ``PE_RLHF_DEBUG=1`` shows the traceback.
"""

from pe_rlhf.baselines import main
from pe_rlhf.training.recipe import run_command_line

if __name__ == "__main__":
    run_command_line(main, "sac_rs")
