"""Every recipe's ``config.yaml`` shows every setting with the value a run gets (issue 43: "every setting visible").

What ``--cfg job`` prints is the schema's defaults, then the file, then the profile (``paper``: nothing) composed;
a field the file leaves out comes from the schema, unseen by a reader of the file. So the composed config, read as
a flat ``{dotted key: value}``, must equal the file's. For PE-RLHF the file also equals the schema's defaults: the
components' defaults are the method the recipe runs (one default per fact).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pe_rlhf.algorithms.baselines.config import load_baseline_config
from pe_rlhf.algorithms.names import PROXY_Q_RECIPES
from pe_rlhf.algorithms.proxy_q.config import load_config
from pe_rlhf.algorithms.proxy_q.config_schema import defaults
from pe_rlhf.runtime.config import to_container

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
RECIPE_NAMES = sorted(p.parent.name for p in RECIPES.glob("*/train.py"))


def flat(tree: dict, prefix: str = "") -> dict[str, object]:
    """``{"optim.lr": 1e-4, ...}``; an empty group stays one entry (``mentor.kwargs: {}``)."""
    out: dict[str, object] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            out.update(flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def shown(recipe: str) -> dict[str, object]:
    values = yaml.safe_load((RECIPES / recipe / "config.yaml").read_text())
    values.pop("defaults")
    return flat(values)


def composed(recipe: str) -> dict[str, object]:
    path = RECIPES / recipe / "config.yaml"
    cfg = load_config(path) if recipe in PROXY_Q_RECIPES else load_baseline_config(recipe, path)
    values = to_container(cfg)
    values.pop("profile")  # the profile group's choice: the defaults list shows it
    return flat(values)


def test_every_recipe_is_checked():
    assert len(RECIPE_NAMES) == 14 and "pe_rlhf" in RECIPE_NAMES


@pytest.mark.parametrize("recipe", RECIPE_NAMES)
def test_config_file_shows_every_setting_with_its_value(recipe):
    file, run = shown(recipe), composed(recipe)
    missing = sorted(set(run) - set(file))
    assert not missing, f"recipes/{recipe}/config.yaml leaves out {missing}"
    assert file == run


def test_pe_rlhf_file_is_the_schema_defaults():
    schema = flat(defaults())
    schema.pop("profile")
    assert shown("pe_rlhf") == schema
