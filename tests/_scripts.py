"""Load a stand-alone script (a recipe's ``train.py``, a ``benchmarks/`` file) as a module, for tests."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script(relative_path: str, name: str | None = None):
    """The module object of ``ROOT / relative_path`` (executed once per call)."""
    path = ROOT / relative_path
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_pe_rlhf_recipe():
    """``recipes/pe_rlhf/train.py`` as a module (its ``main(argv)`` runs the recipe)."""
    return load_script("recipes/pe_rlhf/train.py", "pe_rlhf_recipe")
