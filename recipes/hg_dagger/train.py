"""HG-DAgger baseline recipe (config.yaml beside this file; everything else in pe_rlhf.baselines).

    python recipes/hg_dagger/train.py [profile=paper|cpu|smoke] [group.key=value ...] [--out DIR] [--compare idm-mobil]
    python recipes/hg_dagger/train.py --resume DIR      # continue a run from its last checkpoint
"""

from pe_rlhf.baselines import main

if __name__ == "__main__":
    main("hg_dagger")
