"""Every code block of README.md and docs/guide/*.md runs here, so that a snippet cannot drift from the code.

By language (``_doc_blocks`` reads the blocks and their markers):

- ``python``: executed, in a fresh namespace (or, after ``<!-- docs-test: continue -->``, in the page's previous
  python block's);
- ``bash`` / ``console``: each command is checked without its long run: a recipe command (``python
  recipes/<method>/train.py ...``) parses its flags and composes and validates its config as the script would
  (``--resume DIR``: the flags only, DIR is an example), and a console block's ``error:`` line must be the error
  the composition raises; a ``pe-rlhf`` command parses with the CLI's own parser; ``make TARGET`` names a Makefile
  target; ``python <script>.py`` names a file of the repository; every repository path a command names exists.
  Any other command makes the block fail until it is marked ``<!-- docs-test: skip REASON -->``;
- ``yaml``: parsed; a ``defaults`` list must be a recipe's (``recipes/*/config.yaml``).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import yaml
from _doc_blocks import ROOT, Block, all_blocks

pytestmark = pytest.mark.usefixtures("one_thread_module")

BLOCKS = all_blocks()
PROXY_Q_RECIPES = ("pe_rlhf", "haco", "haim_drl")
RECIPE = re.compile(r"^recipes/(?P<method>\w+)/train\.py$")
REPO_PATH = re.compile(r"^(docs|recipes|examples|benchmarks|src|tests)/")
ASSIGNMENT = re.compile(r"^[A-Z_][A-Z0-9_]*=")


def by_lang(*langs: str) -> list:
    return [pytest.param(b, id=b.id) for b in BLOCKS if b.lang in langs and b.marker != "skip"]


# -- python -------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("block", by_lang("python"))
def test_python_block_runs(block: Block, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # whatever a block writes lands here
    namespace: dict = {"__name__": "__docs__"}
    if block.marker == "continue":
        page_python = [b for b in BLOCKS if b.page == block.page and b.lang == "python" and b.line < block.line]
        assert page_python, f"{block.id}: 'continue' needs an earlier python block on the page"
        exec(compile(page_python[-1].code, page_python[-1].id, "exec"), namespace)
    exec(compile(block.code, block.id, "exec"), namespace)


# -- shell --------------------------------------------------------------------------------------------------------
def commands(block: Block) -> list[tuple[list[str], list[str]]]:
    """``(argv, the output lines shown after it)`` of each command: continuation lines joined, comments dropped; in
    a console block only ``$ `` lines are commands, the others their output."""
    out: list[tuple[list[str], list[str]]] = []
    pending = ""
    for line in block.code.splitlines():
        if block.lang == "console" and not line.startswith("$ ") and not pending:
            if out and line.strip():
                out[-1][1].append(line.strip())
            continue
        line = line[2:] if block.lang == "console" and not pending else line
        pending += line.rstrip("\\").rstrip() + " " if line.rstrip().endswith("\\") else line
        if line.rstrip().endswith("\\"):
            continue
        argv = [a for a in shlex.split(pending, comments=True) if a != "..."]
        pending = ""
        while argv and ASSIGNMENT.match(argv[0]):  # VAR=value before the command
            argv = argv[1:]
        if argv:
            out.append((argv, []))
    return out


def check_paths(argv: list[str]) -> None:
    for arg in argv:
        value = arg.split("=", 1)[1] if "=" in arg and not REPO_PATH.match(arg) else arg
        if REPO_PATH.match(value) and not any(c in value for c in "*?["):
            assert (ROOT / value).exists(), f"{' '.join(argv)}: {value} does not exist"


def check_recipe(method: str, args: list[str], expected: list[str]) -> None:
    from pe_rlhf.runtime.config_rules import ConfigError
    from pe_rlhf.runtime.recipe import parse_command_line

    options, rest = parse_command_line(args)
    if "--cfg" in rest:  # Hydra's print-the-config flag and its value
        i = rest.index("--cfg")
        del rest[i:i + 2]
    assert not [a for a in rest if a.startswith("-")], f"flags left over: {rest}"
    if options.resume:
        return  # the run folder is an example; the flags parsed
    config = ROOT / "recipes" / method / "config.yaml"
    try:
        if method in PROXY_Q_RECIPES:
            from pe_rlhf.algorithms.proxy_q.recipe import load_run_config

            load_run_config(options, rest, config_path=config)
        else:
            from pe_rlhf.algorithms.baselines.cli import load_run_config

            load_run_config(method, options, rest, config_path=config)
    except ConfigError as e:
        assert expected == [f"error: {e}"], f"recipes/{method}/train.py {' '.join(args)}: error: {e}"
        return
    errors = [line for line in expected if line.startswith("error:")]
    assert not errors, f"recipes/{method}/train.py {' '.join(args)} composed; the docs show {errors}"


def check_command(argv: list[str], expected: list[str]) -> None:
    check_paths(argv)
    program = argv[0]
    if program == "make":
        targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
        assert set(argv[1:]) <= targets, f"make {argv[1:]}: targets are {sorted(targets)}"
    elif program == "pe-rlhf":
        from pe_rlhf.apps.cli import build_parser

        try:
            build_parser().parse_args(argv[1:])
        except SystemExit as e:
            pytest.fail(f"{' '.join(argv)}: the CLI refuses it (exit {e.code})")
    elif program == "python" and len(argv) > 1 and RECIPE.match(argv[1]):
        check_recipe(RECIPE.match(argv[1])["method"], argv[2:], expected)
    elif program == "python" and len(argv) > 1 and argv[1].endswith(".py"):
        assert (ROOT / argv[1]).is_file(), f"{argv[1]} does not exist"
    else:
        pytest.fail(f"cannot check `{' '.join(argv)}`: mark its block <!-- docs-test: skip REASON -->")


@pytest.mark.parametrize("block", by_lang("bash", "console", "sh", "shell"))
def test_shell_block_commands_are_valid(block: Block, capsys):
    found = commands(block)
    assert found, f"{block.id}: no command"
    for argv, expected in found:
        check_command(argv, expected)


# -- yaml ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("block", by_lang("yaml", "yml"))
def test_yaml_block_parses_and_its_defaults_are_a_recipes(block: Block):
    data = yaml.safe_load(block.code)
    if isinstance(data, dict) and "defaults" in data:
        recipes = {p.parent.name: yaml.safe_load(p.read_text()).get("defaults")
                   for p in (ROOT / "recipes").glob("*/config.yaml")}
        assert data["defaults"] in recipes.values(), f"{block.id}: defaults {data['defaults']} are no recipe's"


# -- the collector itself -----------------------------------------------------------------------------------------
def test_every_block_is_run_or_marked_with_a_reason():
    runnable = {"python", "bash", "console", "sh", "shell", "yaml", "yml"}
    for block in BLOCKS:
        if block.marker == "skip":
            assert block.reason, f"{block.id}: a skip marker needs a reason"
        else:
            assert block.lang in runnable, f"{block.id}: ```{block.lang} is not run; mark it skip with a reason"
    assert any(b.page.name == "README.md" and b.lang == "python" for b in BLOCKS)


def test_markers_are_read(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("text\n<!-- docs-test: skip needs a person -->\n```python\nraise SystemExit\n```\n\n"
                    "  <!-- docs-test: continue -->\n  ```python\n  x = 1\n  ```\n```text\nnot code\n```\n")
    from _doc_blocks import read_blocks

    blocks = read_blocks(Path(page))
    assert [(b.lang, b.marker, b.reason, b.code) for b in blocks] == [
        ("python", "skip", "needs a person", "raise SystemExit\n"), ("python", "continue", "", "x = 1\n"),
        ("text", None, "", "not code\n")]
