"""PE-RLHF training recipe (HACO with ``selector.enabled=false physics.enabled=false``).

    python recipes/pe_rlhf/train.py [profile=cpu|smoke|paper] [group.key=value ...] [--out DIR]
    python recipes/pe_rlhf/train.py --resume DIR      # continue a killed run from its last checkpoint

Everything reusable lives in ``pe_rlhf.training``; this script hands over to
:func:`pe_rlhf.training.recipe.main` (config: ``recipes/pe_rlhf/config.yaml``, or
``$PE_RLHF_RECIPES/pe_rlhf/config.yaml``). A bad value prints one line ``error: ...`` and exits 2;
``PE_RLHF_DEBUG=1`` shows the traceback.
"""

from __future__ import annotations

from pe_rlhf.training import recipe


def main(argv: list[str] | None = None) -> dict:
    return recipe.main(argv, description=__doc__.splitlines()[0])


if __name__ == "__main__":
    recipe.run_command_line(main)
