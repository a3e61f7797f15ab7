"""Load a stand-alone script (a recipe's ``train.py``, a ``benchmarks/`` file) as a module, or run a recipe as a
user would, for tests."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
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


# A recipe run as a user runs it: this checkout's src first, headless, one thread, no debug tracebacks.
SCRIPT_ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]),
              "SDL_VIDEODRIVER": "dummy", "OMP_NUM_THREADS": "1"}
SCRIPT_ENV.pop("PE_RLHF_DEBUG", None)


def run_recipe(recipe: str, *argv: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python recipes/<recipe>/train.py *argv`` in a fresh process from ``cwd`` (output captured, 300 s)."""
    return subprocess.run([sys.executable, str(ROOT / "recipes" / recipe / "train.py"), *argv], cwd=cwd,
                          env=SCRIPT_ENV, capture_output=True, text=True, timeout=300, check=False)


def run_recipe_here(recipe: str, *argv: str, monkeypatch, capsys) -> tuple[int, str, str]:
    """``python recipes/<recipe>/train.py *argv`` as ``__main__`` in this process (the imports are paid once):
    ``(exit code, stdout, stderr)``. The script's own command line, not a fresh interpreter: one test a path
    keeps :func:`run_recipe` for the process itself (its exit status, nothing imported before it)."""
    import runpy

    script = ROOT / "recipes" / recipe / "train.py"
    monkeypatch.delenv("PE_RLHF_DEBUG", raising=False)
    monkeypatch.setattr(sys, "argv", [str(script), *argv])
    capsys.readouterr()
    code = 0
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
    out, err = capsys.readouterr()
    return code, out, err


def assert_bad_lr_is_one_line(recipe: str, folder: Path, monkeypatch, capsys) -> None:
    """``recipes/<recipe>/train.py optim.lr=-1`` from ``folder``: exit 2, one ``error:`` line naming the field, the
    value and what is allowed, and nothing written."""
    monkeypatch.chdir(folder)
    code, _, err = run_recipe_here(recipe, "optim.lr=-1", "--out", str(folder / "run"), monkeypatch=monkeypatch,
                                   capsys=capsys)
    assert code == 2
    assert err == "error: optim.lr=-1 is invalid: must be a finite number > 0\n"
    assert list(folder.iterdir()) == []
