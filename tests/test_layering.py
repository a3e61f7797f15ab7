"""Package boundaries: the import layers and no import cycle (``lint-imports``, contracts in pyproject.toml), and
no module imports a ``_private`` name from another package of ``pe_rlhf``."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "pe_rlhf"
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"


def _lint_imports(cwd: Path, *args: str, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **({"PYTHONPATH": str(pythonpath)} if pythonpath else {})}
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def test_the_import_layers_and_no_cycle_hold():
    """apps -> algorithms -> runtime -> components -> world -> utilities; inside algorithms, registry -> baselines
    -> proxy_q -> names; and no cycle at any depth."""
    result = _lint_imports(ROOT)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "3 kept, 0 broken" in result.stdout


def test_the_contracts_catch_an_upward_import_and_a_cycle(tmp_path):
    """The same two contract kinds on a tiny package with one upward import that closes a cycle: both break."""
    pkg = tmp_path / "toy"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "high.py").write_text("from toy import low\n")
    (pkg / "low.py").write_text("import toy.high\n")
    (tmp_path / "contracts.toml").write_text(
        '[tool.importlinter]\nroot_package = "toy"\n\n[[tool.importlinter.contracts]]\nname = "layers"\n'
        'type = "layers"\ncontainers = ["toy"]\nlayers = ["high", "low"]\n\n[[tool.importlinter.contracts]]\n'
        'name = "acyclic"\ntype = "acyclic_siblings"\nancestors = ["toy"]\n')
    result = _lint_imports(tmp_path, "--config", "contracts.toml", pythonpath=tmp_path)
    assert result.returncode != 0 and "0 kept, 2 broken" in result.stdout, result.stdout[-2000:]


def _package(path: Path) -> str:
    """The innermost package holding ``path`` (``algorithms/baselines`` and ``algorithms/proxy_q`` are two)."""
    return "/".join(path.relative_to(SRC).parent.parts) or "<top level>"


def _imported_package(module: str) -> str:
    """The innermost package of ``pe_rlhf`` that ``module`` (``pe_rlhf.x.y...``) names or lies in."""
    folder = SRC
    for part in module.split(".")[1:]:
        if not (folder / part).is_dir():
            break
        folder = folder / part
    return "/".join(folder.relative_to(SRC).parts) or "<top level>"


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))  # __version__ is public


def cross_package_private_imports() -> list[str]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not (isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pe_rlhf")):
                continue
            parts = node.module.split(".")
            if _imported_package(node.module) == _package(path):
                continue
            for alias in node.names:
                if _private(alias.name) or any(_private(p) for p in parts[1:]):
                    found.append(f"{path.relative_to(SRC.parent)}:{node.lineno} imports {alias.name} "
                                 f"from {node.module}")
    return found


def test_no_module_imports_a_private_name_from_another_package():
    assert cross_package_private_imports() == []


def test_the_check_sees_a_crossing(tmp_path):
    """The scan itself: a private import across packages is reported, one within a package is not."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "m.py").write_text("from pe_rlhf.b.n import _helper\nfrom pe_rlhf.a.k import _own\n")
    (tmp_path / "b" / "n.py").write_text("def _helper(): pass\n")
    globals()["SRC"], saved = tmp_path, SRC
    try:
        assert cross_package_private_imports() == [f"{tmp_path.name}/a/m.py:1 imports _helper from pe_rlhf.b.n"]
    finally:
        globals()["SRC"] = saved
